#!/usr/bin/env python
"""Learning curves: what accuracy costs in training time, pose-free against posed, and each lever's curve.

    python benchmarks/learning_curves.py [--config conf/demo.yaml conf/demo_from_scratch.yaml]
        [--data outputs/demo] [--size 42] [--steps 20000] [--every 500] [--runs pose-free posed ...]
        [--define NAME='--model.x 1 ...']
        [--data-seeds 0 1 2] [--out outputs/curves] [-- extra `aesplat fit` overrides for every run]

Trains each named run with `aesplat fit` (in this process, one after the other, same config and seed) and
records, with the ``curves.LearningCurve`` callback, PSNR, SSIM, rotation and
translation-direction errors and the copy-the-context yardsticks on the validation scenes and on the test
scenes, side by side, at step 0, every ``--every`` steps and at the end, against steps and training seconds
(evaluation excluded). Writes OUT/<run>/curve.csv per run, OUT/curves.png (validation PSNR and rotation error
against steps and against seconds, one line per run, the yardsticks as horizontal lines) and OUT/CURVES.md: a
table of first and last validation points per run, the run chosen on them (highest validation PSNR at the
last point; the mean over data seeds where there are several; with ``--baseline RUN --margin DB``, another
run only if it beats RUN's validation PSNR by more than DB without a higher validation rotation error) and
that run's test figures, the only test figures the table reports (docs/validation.md). Run it again to
resume: finished
runs are skipped, an interrupted one continues from its last checkpoint (OUT/<run>/checkpoints/last.ckpt,
written at every point) without evaluating its finished points again.

The data: the shards under DATA/shards; when they are missing they are made as `make demo` makes them
(data_prep/synthetic.py into DATA/src with 12 validation scenes and --scene-args, then data_prep/to_shards.py
at --size).

Runs (``--runs``; the levers are the loss and data options that widen the pose signal, each off by default):

    pose-free        the method: ``--model.cameras predicted``
    posed            the same model with the data set's cameras (``--model.cameras dataset``)
    context-views    pose-free + the context views rendered too, loss weight 1 (``model.loss.context_weight``)
    coarse-to-fine   pose-free + a blur of 3 px shrinking to none over the first half of the steps
                     (``model.loss.blur_sigma``, ``model.loss.blur_steps``)
    patch-7          pose-free with 7-pixel patches (``model.net.options.patch_size``): 6x6 tokens at 42 px
    correlation      pose-free with the camera head's view-0 cost volume
                     (``model.net.options.camera_correlation``)
    warm-start       pose-free from the posed warm start (``model.net.weights``): first, once, a fit of
                     ``--warm-start-config`` (conf/demo.yaml conf/warmstart.yaml: the data set's cameras
                     render, the camera head is supervised) for ``--warm-start-steps`` on a disjoint scene
                     set (synthetic.py --seed 1, 1,536 training scenes, in OUT/warm-start-data), resumable;
                     its last.ckpt starts it, with the correlation branch and lr 5e-5
                     (``WARM_START_FINE_TUNE``, as conf/demo.yaml)

``--define NAME='ARGS'`` adds a run of your own (ARGS: `aesplat fit` overrides). ``--data-seeds 0 1 2`` trains
every run once per data seed (``--data.seed``: which training samples are drawn, in which order; the test scenes
and, when the run loads weights, its start stay the same) as RUN@data-seed-S, and CURVES.md adds per run the
mean and the 95 % t-interval over the seeds of its first and last points.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from common import DEMO_VAL_SCENES, demo_shards, t_interval  # noqa: E402
from curves import read_curve  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def lever_args(steps: int) -> dict[str, list[str]]:
    """`aesplat fit` overrides of each named run for a curve of ``steps`` steps."""
    pose_free = ["--model.cameras", "predicted"]
    return {
        "pose-free": pose_free,
        "posed": ["--model.cameras", "dataset"],
        "context-views": [*pose_free, "--model.loss.context_weight", "1.0"],
        "coarse-to-fine": [
            *pose_free,
            "--model.loss.blur_sigma",
            "3.0",
            "--model.loss.blur_steps",
            str(max(1, steps // 2)),
        ],  # fmt: skip
        "patch-7": [*pose_free, "--model.net.options", '{"patch_size": 7}'],
        "correlation": [*pose_free, "--model.net.options", '{"camera_correlation": true}'],
    }


SEED_TAG = "@data-seed-"  # a run trained once per --data-seeds value: pose-free@data-seed-1
WARM_START_SCENES = "--seed 1 --scenes 1536 --test-scenes 8"  # disjoint from the demo's scenes (seed 0)
# The pose-free stage from the warm start, as conf/demo.yaml sets it: its network (the camera head's correlation
# branch) and a learning rate a tenth of the from-scratch one (chosen on validation scenes, docs/validation.md)
WARM_START_FINE_TUNE = ["--model.net.options", '{"camera_correlation": true}', "--model.optim.lr", "5e-5",
                        "--model.optim.appearance_lr", "1e-4"]  # fmt: skip


def warm_start(args: argparse.Namespace) -> Path:
    """The warm-start checkpoint: shards of a disjoint scene set, then `aesplat fit` of ``--warm-start-config``
    to ``--warm-start-steps`` (continuing an interrupted fit). Returns its last.ckpt."""
    from aesplat.lightning_cli import run_lightning

    data = args.out / "warm-start-data"
    shards = ensure_shards(data, args.size, args.warm_start_scene_args)
    run_dir = args.out / "warm-start-pretraining"
    last = run_dir / "checkpoints" / "last.ckpt"
    if last.is_file() and checkpoint_step(last) >= args.warm_start_steps:
        return last
    configs = " + ".join(args.warm_start_config)
    print(f"learning_curves: warm start: {args.warm_start_steps} steps of {configs}", flush=True)
    run_lightning([
        "fit", *config_args(args.warm_start_config), "--data.root", str(shards),
        "--data.image_size", str(args.size),
        "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(args.warm_start_steps),
        "--trainer.limit_val_batches", "0", "--trainer.logger+=CSVLogger", "--trainer.logger.save_dir",
        str(run_dir), "--trainer.logger.name", "", "--trainer.logger.version", "",
        "--trainer.enable_progress_bar", "false", "--checkpoint.save_top_k", "0", "--ckpt_path", "last",
    ])  # fmt: skip
    return last


def checkpoint_step(checkpoint: Path) -> int:
    """The global step a Lightning checkpoint was saved at."""
    import torch

    return int(torch.load(checkpoint, map_location="cpu", weights_only=True).get("global_step", 0))


def ensure_shards(data: Path, size: int, scene_args: str) -> Path:
    """DATA/shards, made like `make demo` makes them when its manifest is missing."""
    demo_shards(data / "src", [(size, data / "shards")], ["--val-scenes", str(DEMO_VAL_SCENES),
                                                           *shlex.split(scene_args)])  # fmt: skip
    return data / "shards"


def config_args(configs: list[str]) -> list[str]:
    """``-c FILE`` for each config file, layered left to right."""
    return [arg for config in configs for arg in ("-c", config)]


def fit_args(
    configs: list[str], shards: Path, size: int, run_dir: Path, steps: int, every: int, extra: list[str]
) -> list[str]:
    """The `aesplat fit` command line of one curve: no validation, no logger, last.ckpt at every point."""
    return [
        "fit", *config_args(configs), "--data.root", str(shards), "--data.image_size", str(size),
        "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(steps),
        "--trainer.limit_val_batches", "0", "--trainer.logger", "false",
        "--trainer.enable_progress_bar", "false",
        "--checkpoint.save_top_k", "0", "--last_checkpoint.every_n_train_steps", str(every),
        "--trainer.callbacks+=curves.LearningCurve",
        "--trainer.callbacks.csv_path", str(run_dir / "curve.csv"),
        "--trainer.callbacks.every_n_steps", str(every),
        *extra, "--ckpt_path", "last",
    ]  # fmt: skip


def finished(csv_path: Path, steps: int) -> bool:
    rows = read_curve(csv_path)
    return bool(rows) and rows[-1]["step"] >= steps


def plot_curves(curves: dict[str, list[dict[str, float]]], path: Path, title: str = "") -> None:
    """PSNR and rotation error against steps and against training seconds; yardsticks as horizontal lines."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5), squeeze=False)
    pre = "val_" if has_validation(curves) else ""  # choices are made on validation figures: plot those
    split = "validation" if pre else "test"
    for i, (name, rows) in enumerate(curves.items()):
        if not rows:
            continue
        color = f"C{i % 10}"
        for col, x_key in enumerate(("step", "train_seconds")):
            x = [r[x_key] for r in rows]
            axes[0, col].plot(x, [r[pre + "psnr"] for r in rows], "o-", ms=3, color=color, label=name)
            rot = [r[pre + "rot_err_deg"] for r in rows]
            if any(math.isfinite(v) for v in rot):
                axes[1, col].plot(x, rot, "o-", ms=3, color=color, label=name)
    rows = next((r for r in curves.values() if r), [])
    if rows:
        for col in range(2):
            ax = axes[0, col]
            ax.axhline(rows[0][pre + "copy_mean_psnr"], color="k", ls="--", lw=1, label="copy: mean of context")
            ax.axhline(rows[0][pre + "copy_best_psnr"], color="k", ls=":", lw=1, label="copy: better context")
    labels = {"step": "training step", "train_seconds": "training seconds (evaluation excluded)"}
    for col, x_key in enumerate(("step", "train_seconds")):
        axes[0, col].set_ylabel(f"{split} PSNR (dB)")
        axes[1, col].set_ylabel(f"{split} rotation error (°)")
        for row in range(2):
            axes[row, col].set_xlabel(labels[x_key])
            axes[row, col].grid(True, alpha=0.3)
            if axes[row, col].lines:
                axes[row, col].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def has_validation(curves: dict[str, list[dict[str, float]]]) -> bool:
    """Whether the curves carry validation figures (shards with a validation split)."""
    return any(math.isfinite(r.get("val_psnr", math.nan)) for rows in curves.values() for r in rows)


def _fmt(v: float, pattern: str) -> str:
    return pattern.format(v) if math.isfinite(v) else "n/a"


def _run_rows(name: str, rows: list[dict[str, float]], pre: str) -> str:
    a, b = rows[0], rows[-1]
    per_step = b["train_seconds"] / b["step"] if b["step"] else math.nan
    return (
        f"| {name} | {int(b['step'])} | {b['train_seconds']:.0f} | {_fmt(per_step, '{:.2f}')} | "
        f"{a[pre + 'psnr']:.2f} → {b[pre + 'psnr']:.2f} | "
        f"{_fmt(a[pre + 'rot_err_deg'], '{:.2f}')} → {_fmt(b[pre + 'rot_err_deg'], '{:.2f}')} "
        f"| {_fmt(a[pre + 'trans_err_deg'], '{:.1f}')} → {_fmt(b[pre + 'trans_err_deg'], '{:.1f}')} |"
    )


def seed_groups(curves: dict[str, list[dict[str, float]]]) -> dict[str, list[list[dict[str, float]]]]:
    """Curves by run: RUN@data-seed-S and plain RUN both under RUN (empty curves left out)."""
    groups: dict[str, list[list[dict[str, float]]]] = {}
    for name, rows in curves.items():
        if rows:
            groups.setdefault(name.partition(SEED_TAG)[0], []).append(rows)
    return groups


def last_mean(seeded: list[list[dict[str, float]]], key: str) -> float:
    """Mean over data seeds of ``key`` at the last point."""
    return sum(rows[-1][key] for rows in seeded) / len(seeded)


def choose(
    curves: dict[str, list[dict[str, float]]], baseline: str | None = None, margin: float = 0.0
) -> str | None:
    """The run with the highest validation PSNR at its last point (mean over its data seeds); None without
    validation figures. Test figures play no part.

    With a ``baseline`` run, another run is chosen over it only if its validation PSNR exceeds the baseline's by
    more than ``margin`` dB and its validation rotation error is not higher (a lever has to earn its place).
    """
    groups = seed_groups(curves)
    scores = {run: last_mean(seeded, "val_psnr") for run, seeded in groups.items()}
    scores = {run: v for run, v in scores.items() if math.isfinite(v)}
    if baseline is not None and baseline in scores:
        rotation = {run: last_mean(groups[run], "val_rot_err_deg") for run in scores}
        scores = {run: v for run, v in scores.items() if run == baseline or (
            v > scores[baseline] + margin and not rotation[run] > rotation[baseline])}  # fmt: skip
    return max(scores, key=scores.get) if scores else None


def summary_table(
    curves: dict[str, list[dict[str, float]]], baseline: str | None = None, margin: float = 0.0
) -> list[str]:
    """Markdown: per run, first and last points (PSNR, rotation and translation errors) and its seconds. With
    validation figures, the rows are validation figures, then the run chosen on them (:func:`choose`) and its
    test figures."""
    pre = "val_" if has_validation(curves) else ""
    split = "validation" if pre else "test"
    lines = [
        f"| run | steps | training s | s/step | {split} PSNR start → end (dB) | {split} rotation error start → "
        f"end (°) | {split} translation error start → end (°) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [_run_rows(name, rows, pre) for name, rows in curves.items() if rows]
    groups = seed_groups(curves)
    for run, seeded in groups.items():
        if len(seeded) >= 2:
            lines.append(_interval_row(run, seeded, pre))
    rows = next((r for r in curves.values() if r), [])
    if not rows:
        return lines
    first = rows[0]
    count = int(first[pre + "num_scenes"])
    lines += ["", f"Copy-the-context yardsticks on the same {count} {split} scenes: mean of the context views "
              f"{first[pre + 'copy_mean_psnr']:.2f} dB, the better context view "
              f"{first[pre + 'copy_best_psnr']:.2f} dB."]  # fmt: skip
    chosen = choose(curves, baseline, margin)
    if chosen is None:
        return lines
    seeded = groups[chosen]
    rule = "highest validation PSNR at the last point"
    if baseline in groups:
        rule += (f"; another run only over **{baseline}**, if its validation PSNR exceeds {baseline}'s by more "
                 f"than {margin:g} dB and its validation rotation error is not higher")  # fmt: skip
    lines += ["", f"Chosen on the validation scenes ({rule}): **{chosen}**. "
              "Its test figures (the only test figures reported here):", "",
              "| run | steps | training s | s/step | test PSNR start → end (dB) | test rotation error start → "
              "end (°) | test translation error start → end (°) |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    lines += [_run_rows(name, rows, "") for name, rows in curves.items()
              if rows and name.partition(SEED_TAG)[0] == chosen]  # fmt: skip
    if len(seeded) >= 2:
        lines.append(_interval_row(chosen, seeded, ""))
    lines += ["", f"Copy-the-context yardsticks on the {int(first['num_scenes'])} test scenes: mean of the "
              f"context views {first['copy_mean_psnr']:.2f} dB, the better context view "
              f"{first['copy_best_psnr']:.2f} dB."]  # fmt: skip
    return lines


def _interval_row(run: str, seeded: list[list[dict[str, float]]], pre: str) -> str:
    steps = max(int(rows[-1]["step"]) for rows in seeded)
    seconds = t_interval(rows[-1]["train_seconds"] for rows in seeded)[0]
    columns = ((pre + "psnr", "{:.2f}"), (pre + "rot_err_deg", "{:.2f}"), (pre + "trans_err_deg", "{:.1f}"))
    cells = [f"{spread(seeded, key, 0, p)} → {spread(seeded, key, -1, p)}" for key, p in columns]
    return (f"| {run}, mean ± 95 % interval over {len(seeded)} data seeds | {steps} | {seconds:.0f} | "
            f"{seconds / steps:.2f} | {' | '.join(cells)} |")  # fmt: skip


def spread(seeded: list[list[dict[str, float]]], key: str, at: int, pattern: str) -> str:
    """Mean and half-width of the 95 % t-interval of one value (``key`` at row ``at``) over seeded curves."""
    mean, half, _ = t_interval(rows[at][key] for rows in seeded)
    if not math.isfinite(mean):
        return "n/a"
    shown = pattern.format(half) if math.isfinite(half) else ""
    return pattern.format(mean) + (f" ± {shown}" if shown and shown != pattern.format(0.0) else "")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1 :]
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", nargs="+", default=["conf/demo.yaml", "conf/demo_from_scratch.yaml"],
                        help="`aesplat fit` config files of every run, layered left to right")  # fmt: skip
    parser.add_argument("--data", type=Path, default=Path("outputs/demo"), help="shards under DATA/shards")
    parser.add_argument("--size", type=int, default=42, help="image side of the shards and of the model input")
    parser.add_argument("--scene-args", default="", help="data_prep/synthetic.py options when making shards")
    parser.add_argument("--steps", type=int, default=20000, help="training steps of every run")
    parser.add_argument("--every", type=int, default=500, help="evaluate and checkpoint every N steps")
    parser.add_argument("--runs", nargs="+", default=["pose-free", "posed"], help="named runs, in this order")
    parser.add_argument("--define", action="append", default=[], metavar="NAME=ARGS",
                        help="a run of your own: NAME='--model.key value ...'")  # fmt: skip
    parser.add_argument("--data-seeds", type=int, nargs="+", default=[], metavar="S",
                        help=f"train every run once per data seed (`--data.seed S`), as RUN{SEED_TAG}S; "
                        "CURVES.md adds each run's mean and 95 %% interval over them")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("outputs/curves"), help="one folder per run, the plot")
    parser.add_argument("--baseline", metavar="RUN",
                        help="choose another run over RUN only if it beats RUN by --margin")  # fmt: skip
    parser.add_argument("--margin", type=float, default=0.0, metavar="DB",
                        help="validation PSNR a run must gain over --baseline, in dB (default 0)")  # fmt: skip
    parser.add_argument("--warm-start-config", nargs="+", default=["conf/demo.yaml", "conf/warmstart.yaml"],
                        help="the warm start's config files, layered left to right")  # fmt: skip
    parser.add_argument("--warm-start-steps", type=int, default=8000, help="steps of the warm start (8000)")
    parser.add_argument("--warm-start-scene-args", default=WARM_START_SCENES,
                        help=f"synthetic.py options of its scenes (default: {WARM_START_SCENES})")  # fmt: skip
    args = parser.parse_args(argv)

    runs = lever_args(args.steps)
    runs["warm-start"] = []  # filled in below, once its checkpoint exists
    for definition in args.define:
        name, sep, overrides = definition.partition("=")
        if not sep or not name:
            parser.error(f"--define takes NAME='ARGS', got {definition!r}")
        runs[name] = shlex.split(overrides)
        if name not in args.runs:
            args.runs.append(name)
    if args.baseline is not None and args.baseline not in args.runs:
        parser.error(f"--baseline {args.baseline} is not one of the runs: {', '.join(args.runs)}")
    unknown = [name for name in args.runs if name not in runs]
    if unknown:
        parser.error(f"unknown run(s) {', '.join(unknown)}; known: {', '.join(runs)} (or --define NAME=ARGS)")

    from aesplat.lightning_cli import run_lightning

    shards = ensure_shards(args.data, args.size, args.scene_args)
    if "warm-start" in args.runs:
        runs["warm-start"] = [
            *runs["pose-free"],
            "--model.net.weights",
            str(warm_start(args)),
            *WARM_START_FINE_TUNE,
        ]
    names = [f"{run}{SEED_TAG}{seed}" for run in args.runs for seed in args.data_seeds] or args.runs
    for name in names:
        run_dir = args.out / name
        csv_path = run_dir / "curve.csv"
        if finished(csv_path, args.steps):
            print(f"learning_curves: {name}: finished ({csv_path})")
            continue
        start = time.perf_counter()
        run, _, seed = name.partition(SEED_TAG)
        overrides = runs[run] + (["--data.seed", seed] if seed else []) + extra
        print(f"learning_curves: {name}: {shlex.join(overrides)}", flush=True)
        run_lightning(fit_args(args.config, shards, args.size, run_dir, args.steps, args.every, overrides))
        print(f"learning_curves: {name}: done in {time.perf_counter() - start:.0f} s wall", flush=True)

    curves = {name: read_curve(args.out / name / "curve.csv") for name in names}
    title = f"{' + '.join(args.config)}, {args.size} px, shards {shards}"
    plot_curves(curves, args.out / "curves.png", title)
    table = summary_table(curves, args.baseline, args.margin)
    (args.out / "CURVES.md").write_text("\n".join([f"# Learning curves ({title})", "", *table]) + "\n")
    print("\n".join(table))
    print(f"learning_curves: wrote {args.out / 'curves.png'} and {args.out / 'CURVES.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
