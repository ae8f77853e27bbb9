"""How many CPU threads torch may use: one policy for every command that computes on the CPU.

torch's default intra-op pool has one thread per core of the machine and spins while it waits for work. On a
shared machine (a 2-core VM with other jobs, a SLURM allocation smaller than the node) those threads fight
the data-loader workers and every other process for the same cores, and a step can take 2-20x longer
(docs/results/training-speed.md). So the commands pick the number themselves:

    intra-op threads = usable cores - data-loader workers, at least 1

where the usable cores are those of the process's affinity mask, capped by ``SLURM_CPUS_PER_TASK`` when set,
and shared by the training processes of one node (``processes``; not when SLURM_CPUS_PER_TASK says what each
task has). ``OMP_NUM_THREADS``, when set, caps the result (torchrun sets it to 1). An explicit number
(``--threads N`` / ``threads: N`` in a config, else the environment variable ``AESPLAT_THREADS``) wins over
all of this. DataLoader worker processes always run one thread (torch sets it in each worker).
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass

ENV_OVERRIDE = "AESPLAT_THREADS"


@dataclass(frozen=True)
class ThreadChoice:
    """The picked intra-op thread count and why (``reason`` is the line the commands print)."""

    threads: int
    reason: str


def usable_cores(env: Mapping[str, str] | None = None, affinity: int | None = None, processes: int = 1) -> int:
    """Cores one process may keep busy: affinity mask, ``SLURM_CPUS_PER_TASK``, shared by ``processes``."""
    env = os.environ if env is None else env
    cores = _affinity() if affinity is None else affinity
    slurm = _positive_int(env, "SLURM_CPUS_PER_TASK")
    if slurm is not None:  # already per task: each task is one training process
        return max(1, min(cores, slurm))
    return max(1, cores // max(1, processes))


def pick_threads(
    num_workers: int = 0,
    override: int | None = None,
    env: Mapping[str, str] | None = None,
    affinity: int | None = None,
    processes: int = 1,
    busy_cores: float = 0.0,
) -> ThreadChoice:
    """The intra-op thread count for a process that feeds ``num_workers`` DataLoader workers.

    ``override`` (a command's ``--threads``) beats ``AESPLAT_THREADS`` beats the automatic choice;
    ``affinity`` (the number of cores in the mask) and ``env`` default to this process's. ``busy_cores``: the
    cores other processes were seen keeping busy (rounded; the automatic choice leaves them alone, so that no
    thread of a parallel region waits for a core).
    """
    env = os.environ if env is None else env
    if override is not None:
        if override < 1:
            raise ValueError(f"threads must be >= 1, got {override}")
        return ThreadChoice(override, f"{override} (set by --threads / the config's `threads`)")
    from_env = _positive_int(env, ENV_OVERRIDE)
    if from_env is None and env.get(ENV_OVERRIDE, "").strip():
        raise ValueError(f"{ENV_OVERRIDE}={env[ENV_OVERRIDE]!r}: give a positive number of threads or unset it")
    if from_env is not None:
        return ThreadChoice(from_env, f"{from_env} (set by {ENV_OVERRIDE})")
    cores = usable_cores(env, affinity, processes)
    busy = max(0, math.floor(busy_cores + 0.5))  # half a core or more counts as one
    threads = max(1, cores - max(0, num_workers) - busy)
    reason = f"{cores} usable cores - {num_workers} data-loader workers"
    if busy:
        reason += f" - {busy} kept busy by other processes"
    omp = _positive_int(env, "OMP_NUM_THREADS")
    if omp is not None and omp < threads:
        threads, reason = omp, f"{reason}, capped by OMP_NUM_THREADS={omp}"
    return ThreadChoice(threads, f"{threads} ({reason}; override with --threads or {ENV_OVERRIDE})")


_applied: int | None = None


def apply_thread_policy(
    num_workers: int = 0,
    override: int | None = None,
    processes: int = 1,
    quiet: bool = False,
    busy_cores: float = 0.0,
) -> int:
    """Pick (``pick_threads``) and set torch's intra- and inter-op thread counts; print the choice once per
    process (again only if it changes). Returns the intra-op count."""
    import torch

    global _applied
    try:
        choice = pick_threads(num_workers, override, processes=processes, busy_cores=busy_cores)
    except ValueError as err:  # a user's setting: name it, no traceback
        raise SystemExit(f"aesplat: {err}") from err
    torch.set_num_threads(choice.threads)
    try:  # inter-op threads (only used by explicit torch.jit.fork work) cannot change once any was used
        torch.set_num_interop_threads(choice.threads)
    except RuntimeError:
        pass
    if not quiet and _applied != choice.threads:
        print(f"aesplat: torch CPU threads: {choice.reason}", file=sys.stderr)
    _applied = choice.threads
    return choice.threads


def _affinity() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _positive_int(env: Mapping[str, str], name: str) -> int | None:
    """``env[name]`` as a positive int; None when unset, empty or not a positive integer (SLURM may write
    e.g. "2(x3)" in some variables; OMP_NUM_THREADS may list nesting levels "4,2": the first is used)."""
    raw = env.get(name, "").strip().split(",")[0]
    try:
        value = int(raw)
    except ValueError:
        return None
    return value if value >= 1 else None
