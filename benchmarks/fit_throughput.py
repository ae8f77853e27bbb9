"""Seconds per step of `aesplat fit` itself (Lightning, callbacks, logging), read from the run's own logs.

    python benchmarks/fit_throughput.py -c conf/re10k.yaml --out outputs/fit-throughput --steps 300
    python benchmarks/fit_throughput.py -c conf/smoke.yaml --out /tmp/fit --steps 20 --window 5 -- \
        --trainer.accelerator cpu                                          # extra `aesplat fit` arguments
    python benchmarks/fit_throughput.py -c conf/re10k.yaml --out OUT/fit-3 --shards OUT/shards \
        --json OUT/fit-3.json -- --data.num_context_views 3 --model.net.view_aggregation pool

Writes synthetic scenes as shards at the config's image size into OUT/shards (or ``--shards``; kept for the
next call), then runs the product's command line, printed before it starts:

    aesplat fit -c CONFIG --data.root OUT/shards --trainer.max_steps STEPS --trainer.logger+=CSVLogger ...

with the curriculum widened to the gaps the synthetic scenes hold, validation and checkpoints off (a ``large``
checkpoint is about 12 GB) and the run's logs in OUT/run/metrics.csv. The ``Throughput`` callback logs
``train/sec_per_step``, ``train/samples_per_sec`` and ``train/peak_memory_gib`` over windows of ``--window``
steps (the logging interval and the CSV logger's flush are set to the same, so each window is written once, as
it ends: a run stopped early leaves the windows it finished in metrics.csv). The report is the median
over the windows after the first (the first holds compilation and warm-up), the peak memory and the skipped
steps (``train/skipped_steps``, which the module logs). ``--json`` also writes them, with the command, the
context views, the GPU and the versions (``provenance()``), whole or not at all.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

import yaml
from common import AESPLAT, provenance, synthetic_shards, versions, write_whole

from aesplat.train.loss import vgg16_weights_path


def data_setting(config: list[str], key: str, default):
    """``data.KEY`` of the layered configs (the last that sets it), else ``default``."""
    for path in config:
        default = ((yaml.safe_load(Path(path).read_text()) or {}).get("data") or {}).get(key, default)
    return default


def shards_for(config: list[str], root: Path) -> tuple[Path, list[int]]:
    """Synthetic shards at the configs' image size in ``root/shards`` (made once); the gap range they hold."""
    size = data_setting(config, "image_size", 224)
    shards, gaps_file = root / "shards", root / "shards" / "gaps.txt"
    if not gaps_file.is_file():
        gaps_file.write_text(" ".join(str(g) for g in synthetic_shards(root, size, scenes=4)[1]))
    return shards, [int(g) for g in gaps_file.read_text().split()]


def fit_command(config: list[str], shards: Path, gaps: list[int], run_dir: Path, steps: int, window: int,
                extra: list[str]) -> list[str]:  # fmt: skip
    gap = f"[{gaps[0]}, {gaps[1]}]"
    return [
        "aesplat", "fit", *(a for c in config for a in ("-c", c)), "--data.root", str(shards),
        "--data.gap_initial", gap, "--data.gap_final", gap, "--trainer.max_steps", str(steps),
        "--data.train_batches_per_epoch", str(steps), "--trainer.default_root_dir", str(run_dir),
        "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
        "--checkpoint.save_top_k", "0", "--last_checkpoint.save_last", "false",
        "--trainer.logger+=CSVLogger", "--trainer.logger.save_dir", str(run_dir), "--trainer.logger.name", "",
        "--trainer.logger.version", "", "--trainer.logger.flush_logs_every_n_steps", str(window),
        "--trainer.log_every_n_steps", str(window), "--throughput.window",
        str(window), "--trainer.enable_progress_bar", "false", *extra,
    ]  # fmt: skip


def summarize(metrics_csv: Path) -> dict[str, float | int | str]:
    """The figures of a run from its metrics.csv: medians over the windows after the first. A run stopped by a
    signal logs its last window again at the step it stopped, with the same values: that row is not a window."""
    with metrics_csv.open(newline="") as f:
        rows = list(csv.DictReader(f))
    timing = ("train/sec_per_step", "train/samples_per_sec", "train/peak_memory_gib")
    windows = [[r.get(k) for k in timing] for r in rows if r.get(timing[0]) not in (None, "")]
    windows = [[float(v or "nan") for v in w] for i, w in enumerate(windows) if i == 0 or w != windows[i - 1]]

    def column(key: str) -> list[float]:
        return [float(r[key]) for r in rows if r.get(key) not in (None, "")]

    seconds, samples, memory = ([w[i] for w in windows] for i in range(3))
    if len(seconds) < 2:
        raise SystemExit(f"{metrics_csv}: {len(seconds)} throughput window(s); run more steps than 2 windows")
    skipped = column("train/skipped_steps")
    return {
        "windows after the first": len(seconds) - 1,
        "seconds per step (median)": statistics.median(seconds[1:]),
        "seconds per step (min - max)": f"{min(seconds[1:]):.3f} - {max(seconds[1:]):.3f}",
        "samples / s (median)": statistics.median(samples[1:]),
        "first window, s / step (compilation, warm-up)": seconds[0],
        "peak memory (GiB)": max((m for m in memory if not math.isnan(m)), default=float("nan")),
        "skipped steps": int(skipped[-1]) if skipped else "not logged",
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", "-c", action="append", required=True, help="config file(s), layered")
    p.add_argument("--out", type=Path, required=True, help="shards and the run go here")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--window", type=int, default=50, help="steps per throughput window (and logging interval)")
    p.add_argument("--shards", type=Path, help="make (once) and read the synthetic shards here (default: OUT)")
    p.add_argument("--json", type=Path, help="also write the figures, the command and the versions here")
    p.add_argument("extra", nargs="*", help="more `aesplat fit` arguments, after --")
    args = p.parse_args()
    if args.steps < 2 * args.window:
        raise SystemExit(f"--steps {args.steps}: need at least two windows of {args.window} steps")
    run_dir = args.out / "run"
    if run_dir.exists():
        raise SystemExit(f"{run_dir} exists: remove it (or pick another --out) to measure again")
    shards, gaps = shards_for(args.config, args.shards or args.out)
    extra = list(args.extra)
    if not vgg16_weights_path().is_file():  # as bench_train_step.py does: time it without LPIPS
        print(
            f"note: LPIPS weights missing ({vgg16_weights_path()}); timing with lpips_weight 0", file=sys.stderr
        )
        extra = ["--model.loss.lpips_weight", "0", "--model.eval.metrics_lpips", "false", *extra]
    command = fit_command(args.config, shards, gaps, run_dir, args.steps, args.window, extra)
    print(f"$ {shlex.join(command)}\n", flush=True)
    env = {**os.environ, "WANDB_MODE": "disabled"}
    subprocess.run([*AESPLAT, *command[1:]], check=True, env=env)
    figures = summarize(run_dir / "metrics.csv")
    print(f"\n## aesplat fit {' '.join(f'-c {c}' for c in args.config)}: {args.steps} steps, "
          f"windows of {args.window}\n")  # fmt: skip
    print("| measure | value |\n| --- | ---: |")
    for key, value in figures.items():
        print(f"| {key} | {value:.3f} |" if isinstance(value, float) else f"| {key} | {value} |")
    if args.json:
        record = {"command": shlex.join(command), "context_views": context_views(args.config, extra),
                  "figures": figures, "versions": versions(), **provenance()}  # fmt: skip
        write_whole(args.json, (json.dumps(record, indent=2) + "\n").encode())


def context_views(config: list[str], extra: list[str]) -> int | list[int]:
    """The run's ``data.num_context_views``: the last ``--data.num_context_views`` given, else the configs'."""
    views = data_setting(config, "num_context_views", 2)
    for flag, value in zip(extra, extra[1:]):
        if flag == "--data.num_context_views":
            views = yaml.safe_load(value)
    return views


if __name__ == "__main__":
    main()
