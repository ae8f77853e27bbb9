"""The thread policy under contention: the demo fit alone and beside one busy single-threaded process.

    python benchmarks/bench_threads.py [--steps 100 --repeats 2 --variants off,on]

Runs `aesplat fit -c conf/demo.yaml` (42x42 shards made as `make demo` makes them, ``--steps`` steps, no
validation, no logger) in a subprocess and times the whole command. Variants:

- ``off``: torch's default thread count (one per core), as before the policy (``AESPLAT_THREADS`` set to it);
- ``on``: the policy (usable cores minus data-loader workers);
- ``N`` (a number): ``AESPLAT_THREADS=N``.

Each variant runs quiet and beside ``python -c "while True: pass"``; runs are interleaved (repeat, variant,
condition) so a change in the machine's load hits every variant alike. The load average before each run is
printed: on a shared machine "quiet" only means "no competitor of ours".
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import AESPLAT, demo_shards

REPO = Path(__file__).resolve().parents[1]
BUSY = "while True: pass"


def make_shards(root: Path, size: int) -> Path:
    """The demo's data: data_prep/synthetic.py defaults, then 42x42 shards (as `make demo`)."""
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    demo_shards(root / "src", [(size, root / "shards")], [], cwd=REPO, env=_env(), **quiet)
    return root / "shards"


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("AESPLAT_THREADS", "OMP_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO / "src"), env.get("PYTHONPATH")]))
    return {**env, "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore", **extra}


def fit_seconds(shards: Path, run_dir: Path, steps: int, size: int, threads: str | None) -> float:
    """Wall time of one `aesplat fit` of the demo config (imports and start-up included)."""
    cmd = [*AESPLAT, "fit", "-c", "conf/demo.yaml", "--data.root", str(shards),
           "--data.image_size", str(size), "--trainer.default_root_dir", str(run_dir),
           "--trainer.max_steps", str(steps), "--trainer.logger", "false", "--trainer.enable_progress_bar",
           "false", "--trainer.check_val_every_n_epoch", "1000000"]  # fmt: skip
    env = _env(**({"AESPLAT_THREADS": threads} if threads else {}))
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    took = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"fit failed:\n{proc.stderr[-4000:]}")
    return took


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--size", type=int, default=42)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--variants", default="off,on", help="comma list of off | on | N threads")
    p.add_argument("--conditions", default="quiet,busy", help="comma list of quiet | busy")
    p.add_argument("--data", default=None, help="folder for the demo data (default: a temporary one)")
    a = p.parse_args()

    import torch

    default_threads = str(torch.get_num_threads())  # torch's own choice in a fresh process: one per core
    variants = a.variants.split(",")
    conditions = a.conditions.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(a.data) if a.data else Path(tmp) / "data"
        shards = make_shards(data, a.size)
        times: dict[tuple[str, str], list[float]] = {(v, c): [] for v in variants for c in conditions}
        print(f"demo fit, {a.steps} steps at {a.size}^2, {os.cpu_count()} CPUs, torch default "
              f"{default_threads} threads\n")  # fmt: skip
        print("| repeat | variant | condition | load avg (1 min) | wall s |\n| --- | --- | --- | ---: | ---: |")
        for r in range(a.repeats):
            for v in variants:
                for c in conditions:
                    threads = {"off": default_threads, "on": None}.get(v, v)
                    load = os.getloadavg()[0]
                    busy = subprocess.Popen([sys.executable, "-c", BUSY]) if c == "busy" else None
                    try:
                        took = fit_seconds(shards, Path(tmp) / "run", a.steps, a.size, threads)
                    finally:
                        if busy is not None:
                            busy.kill()
                            busy.wait()
                    times[(v, c)].append(took)
                    print(f"| {r} | {v} | {c} | {load:.1f} | {took:.1f} |", flush=True)
        print("\n| variant | " + " | ".join(f"{c} (median s)" for c in conditions) + " | busy / quiet |")
        print("| --- | " + " | ".join("---:" for _ in conditions) + " | ---: |")
        for v in variants:
            med = {c: statistics.median(times[(v, c)]) for c in conditions}
            ratio = f"{med['busy'] / med['quiet']:.2f}" if {"busy", "quiet"} <= set(med) else ""
            print(f"| {v} | " + " | ".join(f"{med[c]:.1f}" for c in conditions) + f" | {ratio} |")


if __name__ == "__main__":
    main()
