"""How many CPU threads torch may use: one policy for every command that computes on the CPU.

torch's default intra-op pool has one thread per core of the machine and spins while it waits for work. On a
shared machine (a 2-core VM with other jobs, a SLURM allocation smaller than the node) those threads fight
the data-loader workers and every other process for the same cores, and a step can take 2-20x longer
(benchmarks/RESULTS.md, "Thread policy"). So the commands pick the number themselves:

    intra-op threads = usable cores - data-loader workers, at least 1

where the usable cores are those of the process's affinity mask, capped by ``SLURM_CPUS_PER_TASK`` when set,
and shared by the training processes of one node (``processes``; not when SLURM_CPUS_PER_TASK says what each
task has). ``OMP_NUM_THREADS``, when set, caps the result (torchrun sets it to 1). An explicit number
(``--threads N`` / ``threads: N`` in a config, else the environment variable ``AESPLAT_THREADS``) wins over
all of this. DataLoader worker processes always run one thread (torch sets it in each worker).

The picked count is the safe one, not always the fastest: on a quiet machine the data worker is mostly idle
and one more thread makes a small model's step ~10 % faster. So ``aesplat fit`` with the automatic choice
also measures (``ThreadTuner``): it times the training steps at the picked count and at all usable cores,
keeps the faster, measures again every ``period`` steps, and at once when the step time rises by half
(something else started on the machine). An explicit number turns the measuring off.
"""

from __future__ import annotations

import os
import statistics
import sys
from collections.abc import Iterable, Mapping
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
) -> ThreadChoice:
    """The intra-op thread count for a process that feeds ``num_workers`` DataLoader workers.

    ``override`` (a command's ``--threads``) beats ``AESPLAT_THREADS`` beats the automatic choice;
    ``affinity`` (the number of cores in the mask) and ``env`` default to this process's.
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
    threads = max(1, cores - max(0, num_workers))
    reason = f"{cores} usable cores - {num_workers} data-loader workers"
    omp = _positive_int(env, "OMP_NUM_THREADS")
    if omp is not None and omp < threads:
        threads, reason = omp, f"{reason}, capped by OMP_NUM_THREADS={omp}"
    return ThreadChoice(threads, f"{threads} ({reason}; override with --threads or {ENV_OVERRIDE})")


def tuning_candidates(
    num_workers: int = 0, override: int | None = None, env: Mapping[str, str] | None = None,
    affinity: int | None = None, processes: int = 1,
) -> tuple[int, ...]:  # fmt: skip
    """The thread counts ``ThreadTuner`` chooses between for a fit: (picked, usable cores), or only the picked
    count when it was set explicitly (``override``, ``AESPLAT_THREADS``, ``OMP_NUM_THREADS``), when several
    training processes share the node (their steps wait for each other, so one process's timing says little)
    or when the two are the same."""
    env = os.environ if env is None else env
    picked = pick_threads(num_workers, override, env, affinity, processes).threads
    explicit = override is not None or any(_positive_int(env, k) for k in (ENV_OVERRIDE, "OMP_NUM_THREADS"))
    if explicit or processes > 1:
        return (picked,)
    return tuple(sorted({picked, usable_cores(env, affinity, processes)}))


class ThreadTuner:
    """Pick the intra-op thread count by timing training steps (pure logic; the fit's callback applies it).

    A round measures every candidate: after a switch ``settle`` steps are not counted, then ``probe`` steps
    give the candidate's median step time. The fastest wins; one within ``margin`` of it with fewer threads
    wins instead (fewer threads are the safer choice when the machine gets busy). Then the winner runs, and a
    new round starts after ``period`` steps (doubled, up to 8x, each time a round confirms the same winner:
    measuring the slower count costs steps), or as soon as the median of the last ``probe`` steps exceeds
    ``slowdown`` x the winner's measured time while the winner is not the fewest threads (more contention
    never favours more threads, so at the fewest the slower time only becomes the new yardstick).
    ``observe`` takes each step's seconds and returns the count to switch to, or None.
    """

    def __init__(
        self, candidates: Iterable[int], probe: int = 8, settle: int = 2, period: int = 300,
        slowdown: float = 1.5, margin: float = 0.03,
    ) -> None:  # fmt: skip
        self.candidates = tuple(sorted(set(candidates)))
        if not self.candidates or min(self.candidates) < 1:
            raise ValueError(f"thread counts must be >= 1, got {candidates}")
        if probe < 1 or settle < 0 or period < 1 or slowdown <= 1 or margin < 0:
            raise ValueError("need probe >= 1, settle >= 0, period >= 1, slowdown > 1, margin >= 0")
        self.probe, self.settle, self.period = probe, settle, period
        self.slowdown, self.margin = slowdown, margin
        self.current = self.candidates[0]  # the policy's pick: the safe start
        self.steps_at: dict[int, int] = dict.fromkeys(self.candidates, 0)
        self.last_round: dict[int, float] = {}  # candidate -> median seconds per step of the latest round
        self.rounds = 0
        self._queue: list[int] = []
        self._reference: float | None = None  # the winner's median: the yardstick of the slowdown check
        self._samples: list[float] = []
        self._skip = 0
        self._since_round = 0
        self._period = period  # the current wait between rounds (backs off while the winner stays the same)
        self._winner: int | None = None
        if len(self.candidates) > 1:
            self._start_round(measured={}, skip=settle + 1)  # the first step also pays one-off set-up

    @property
    def active(self) -> bool:
        return len(self.candidates) > 1

    @property
    def probing(self) -> bool:
        return self._reference is None

    def observe(self, seconds: float) -> int | None:
        self.steps_at[self.current] += 1
        if not self.active:
            return None
        if self._skip > 0:
            self._skip -= 1
            return None
        self._samples.append(seconds)
        if self.probing:
            if len(self._samples) < self.probe:
                return None
            self._round[self.current] = statistics.median(self._samples)
            if self._queue:
                return self._switch(self._queue.pop(0))
            return self._finish_round()
        self._samples = self._samples[-self.probe :]
        self._since_round += 1
        recent = statistics.median(self._samples) if len(self._samples) == self.probe else None
        slowed = recent is not None and recent > self.slowdown * self._reference
        if slowed and self.current == self.candidates[0]:
            self._reference = recent  # busier, and already at the fewest threads: nothing faster to try
            return None
        if slowed:
            self._period = self.period
        if self._since_round >= self._period or slowed:
            return self._start_round(measured={self.current: recent} if recent is not None else {})
        return None

    def _start_round(self, measured: dict[int, float], skip: int = 0) -> int | None:
        self._round = dict(measured)
        self._reference = None
        self._queue = [c for c in self.candidates if c not in self._round]
        if self.current in self._queue:  # measure where we are first: no switch needed
            self._queue.remove(self.current)
            self._samples, self._skip = [], skip
            return None
        return self._switch(self._queue.pop(0))

    def _finish_round(self) -> int | None:
        self.rounds += 1
        self.last_round = dict(self._round)
        fastest = min(self._round.values())
        best = min(c for c, t in self._round.items() if t <= fastest * (1 + self.margin))
        self._period = min(2 * self._period, 8 * self.period) if best == self._winner else self.period
        self._winner = best
        self._reference = self._round[best]
        self._since_round = 0
        if best == self.current:
            self._samples = []
            return None
        return self._switch(best)

    def _switch(self, threads: int) -> int:
        self.current, self._samples, self._skip = threads, [], self.settle
        return threads


_applied: int | None = None


def apply_thread_policy(
    num_workers: int = 0, override: int | None = None, processes: int = 1, quiet: bool = False
) -> int:
    """Pick (``pick_threads``) and set torch's intra- and inter-op thread counts; print the choice once per
    process (again only if it changes). Returns the intra-op count."""
    import torch

    global _applied
    try:
        choice = pick_threads(num_workers, override, processes=processes)
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
