#!/usr/bin/env python
"""Write the `make demo` report: what the CPU demo run learned, how long it took, and what accuracy costs.

    python scripts/demo_report.py --run-dir outputs/demo/run --initial outputs/demo/initial/test-latest \
        [--bench outputs/demo/bench] [--timings outputs/demo/timings.csv] [--out outputs/demo]

Reads the run directory `aesplat fit` wrote (config.yaml, metrics.csv from the CSV logger, checkpoints/, and
test-latest/: the link to the newest test-<UTC time>/ folder of `aesplat test`), the untrained model's
`aesplat test` output (--initial), and optionally an `aesplat bench` folder and the stage timings the Makefile
recorded. Writes into --out:

    REPORT.md          metrics of the untrained and the trained model, the PSNR gain, timings, figures
    render_grid.png    per test scene: context views | target | untrained render | trained render | depth
    loss_curve.png     training loss and PSNR over steps (validation PSNR and the untrained test PSNR marked)
    demo.json          the report's figures as data, with the date, the commit, the machine and its load
    headline.md        the headline table (random initialisation, warm start, trained)

With ``--results DIR`` (`make demo DEMO_RESULTS=docs/results/demo`) it also writes demo.json, headline.md and
render_grid.png into DIR, each whole or not at all: the files the documentation pages read their demo
figures from (scripts/figures.py).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

import matplotlib

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from common import provenance, write_whole  # noqa: E402
from curves import COPY_BEST, COPY_MEAN, context_copy_psnr  # noqa: E402

from aesplat.bench.command import evaluation_scenes  # noqa: E402
from aesplat.checkpoint import LoadedCheckpoint, load_checkpoint, run_config  # noqa: E402
from aesplat.images import colorize_depth  # noqa: E402
from aesplat.model import forward_batch  # noqa: E402
from aesplat.render import render  # noqa: E402
from aesplat.train.metrics import psnr  # noqa: E402

CAMERAS = {"predicted": "*predicted* target cameras", "dataset": "data set's target cameras"}  # model.cameras
# The demo's two goals: PSNR at least this much over copying the mean of the context views, and a rotation
# error at most this fraction of the randomly initialised model's.
GOAL_DB_OVER_MEAN_COPY = 2.0
GOAL_ROTATION_RATIO = 0.5
# The Gaussians form a scene, not a screen-space point lattice (docs/evaluation.md): at most a tenth of them
# below 0.1 px in their own view, and rendered at twice the size no worse than 0.5 dB below the 1x render
# upsampled.
GOAL_MAX_SUBPIXEL_SHARE = 0.10
GOAL_MIN_TRANSFER_GAIN_DB = -0.5
METRIC_ROWS = [  # key in summary.json, label, format, True when higher is better
    ("psnr", "PSNR (dB) ↑", "{:.2f}", True),
    ("ssim", "SSIM ↑", "{:.4f}", True),
    ("lpips", "LPIPS ↓", "{:.4f}", False),
    ("rot_err_deg", "rotation error (°) ↓", "{:.2f}", False),
    ("trans_err_deg", "translation error (°) ↓", "{:.2f}", False),
]


# ---------------------------------------------------------------------------------------------------
# Inputs


def find_checkpoint(run_dir: Path) -> Path:
    """last.ckpt of the run (what `make demo` tests: 600 steps, fixed), else its newest best checkpoint
    (picked on the validation split, when the shards have one)."""
    folder = run_dir / "checkpoints"
    if (folder / "last.ckpt").is_file():
        return folder / "last.ckpt"
    best = sorted(folder.glob("best*.ckpt"), key=lambda p: p.stat().st_mtime)
    if best:
        return best[-1]
    raise SystemExit(f"demo_report: no checkpoint in {folder}; did `aesplat fit` run?")


def read_summary(test_dir: Path) -> dict:
    path = test_dir / "summary.json"
    if not path.is_file():
        raise SystemExit(f"demo_report: {path} is missing; run `aesplat test` first")
    return json.loads(path.read_text())


def read_per_scene(test_dir: Path) -> dict[str, float]:
    """scene -> PSNR from `aesplat test`'s per_scene.csv."""
    with open(test_dir / "per_scene.csv") as f:
        return {row["scene"]: float(row["psnr"]) for row in csv.DictReader(f) if row["psnr"]}


def read_metrics(run_dir: Path) -> list[dict[str, float]]:
    """The CSV logger's metrics.csv rows (empty cells dropped); [] when the run used no CSV logger."""
    found = sorted(run_dir.glob("**/metrics.csv"), key=lambda p: p.stat().st_mtime)
    if not found:
        return []
    with open(found[-1]) as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]


WALL_CLOCK = "wall clock"  # the timings row of the whole pipeline (scripts/demo.sh)


def read_timings(path: Path | None) -> list[tuple[str, float]]:
    if path is None or not path.is_file():
        return []
    with open(path) as f:
        return [(row["stage"], float(row["seconds"])) for row in csv.DictReader(f)]


def timings_section(timings: list[tuple[str, float]], steps: int) -> list[str]:
    """The report's timings table. `make demo` ends it with the whole pipeline's wall time (a ``wall clock``
    row): its diagnostic stages run beside the method's, so the stages add up to more than that."""
    if not timings:
        return []
    wall = [s for stage, s in timings if stage.startswith(WALL_CLOCK)]
    stages = [(stage, s) for stage, s in timings if not stage.startswith(WALL_CLOCK)]
    total = wall[-1] if wall else sum(s for _, s in stages)
    label = "total (wall clock; the diagnostic ran beside the method)" if wall else "total"
    lines = ["## Timings", "", "| stage | wall time |", "| --- | ---: |"]
    lines += [f"| {stage} | {seconds:.0f} s |" for stage, seconds in stages]
    lines += [f"| **{label}** | **{total:.0f} s ({total / 60:.1f} min)** |", ""]
    fit = dict(stages).get("aesplat fit")
    if fit and steps > 0:
        lines += [f"Training: {steps} steps in {fit:.0f} s ({fit / steps:.2f} s per step, start-up and "
                  "validation included).", ""]  # fmt: skip
    return lines


def initial_model(config: dict, device: torch.device) -> torch.nn.Module:
    """The untrained model exactly as `aesplat fit` started: the run's seed, then the model build."""
    from lightning.pytorch import seed_everything

    from aesplat.model import NetConfig

    net = dict(config["model"]["net"])
    seed = config.get("seed_everything")
    if isinstance(seed, int) and not isinstance(seed, bool):
        seed_everything(seed, verbose=False)
    model = NetConfig(**{**net, "compile": "none"}).build()  # the run's network settings, every one of them
    return model.to(device).eval()


# ---------------------------------------------------------------------------------------------------
# Figures


@torch.no_grad()
def render_grid(
    trained: LoadedCheckpoint, untrained: torch.nn.Module, scenes: list, path: Path, start: str = "untrained"
) -> dict:
    """Rows of context | target | untrained render | trained render | trained depth; returns per-scene PSNRs.
    Both models render with the trained run's cameras (``model.cameras``: predicted or the data set's)."""
    columns = ["context 0", "context 1", "target", f"{start} render", "trained render", "rendered depth"]
    fig, axes = plt.subplots(len(scenes), len(columns), figsize=(2.2 * len(columns), 2.3 * len(scenes)),
                             squeeze=False)  # fmt: skip
    options = trained.render_options()
    options.pop("compile", None)
    psnrs: dict[str, dict[str, float]] = {}
    for row, scene in enumerate(scenes):
        ctx, tgt = scene.context.images, scene.target.images
        size = tgt.shape[-1]
        tiles, values = [ctx[0, 0], ctx[0, 1], tgt[0, 0]], {}
        for name, model in (("untrained", untrained), ("trained", trained.model)):
            out = forward_batch(model, scene, trained.cameras)
            vc = ctx.shape[1]
            rendered = render(out.gaussians, out.extrinsics[:, vc:], out.intrinsics[:, vc:], size, size,
                              **options)  # fmt: skip
            values[name] = psnr(rendered.color[0], tgt[0]).mean().item()
            tiles.append(rendered.color[0, 0])
        psnrs[scene.scene[0]] = values
        depth = torch.from_numpy(colorize_depth(rendered.depth[0, 0, 0])).permute(2, 0, 1).float() / 255
        tiles.append(depth)
        for col, tile in enumerate(tiles):
            ax = axes[row, col]
            ax.imshow(tile.clamp(0, 1).permute(1, 2, 0).cpu().numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(columns[col], fontsize=9)
            if col == 0:
                ax.set_ylabel(scene.scene[0][:18], fontsize=7)
        axes[row, 3].set_xlabel(f"{values['untrained']:.2f} dB", fontsize=8)
        axes[row, 4].set_xlabel(f"{values['trained']:.2f} dB", fontsize=8)
    cameras = CAMERAS[trained.cameras].replace("*", "")  # markdown emphasis means nothing in a plot title
    title = (f"test scenes: renders of the first target view with the {cameras} "
             "(PSNR over all targets)")  # fmt: skip
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return psnrs


def smooth(values: list[float], window: int) -> list[float]:
    """Trailing moving average."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


def loss_curve(metrics: list[dict[str, float]], initial_psnr: float, trained_psnr: float, path: Path) -> bool:
    """Training loss (log scale) and PSNR against the step; False when there are no training rows."""
    train = [r for r in metrics if "train/loss" in r and "step" in r]
    if not train:
        return False
    val = [r for r in metrics if "val/psnr" in r and "step" in r]
    steps = [r["step"] for r in train]
    window = max(1, min(50, len(train) // 8))  # batch losses of a few scenes are noisy: show the trend
    fig, (ax_loss, ax_psnr) = plt.subplots(1, 2, figsize=(12, 4.2))
    loss = [r["train/loss"] for r in train]
    ax_loss.plot(steps, loss, color="C0", alpha=0.3, label="train loss")
    ax_loss.plot(steps, smooth(loss, window), color="C0", label=f"moving average ({window} logged steps)")
    ax_loss.set_yscale("log")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss (MSE + λ·LPIPS)")
    ax_loss.grid(True, which="both", alpha=0.3)
    ax_loss.legend()
    if any("train/psnr" in r for r in train):
        tp = [r.get("train/psnr", math.nan) for r in train]
        ax_psnr.plot(steps, tp, color="C1", alpha=0.3, label="train PSNR (batch)")
        ax_psnr.plot(steps, smooth(tp, window), color="C1", label="train PSNR (moving average)")
    if val:
        ax_psnr.plot([r["step"] for r in val], [r["val/psnr"] for r in val], "o-", color="C2", label="val PSNR")
    ax_psnr.axhline(initial_psnr, color="k", linestyle="--", label=f"untrained test PSNR {initial_psnr:.2f}")
    ax_psnr.axhline(trained_psnr, color="C3", linestyle=":", label=f"trained test PSNR {trained_psnr:.2f}")
    ax_psnr.set_xlabel("step")
    ax_psnr.set_ylabel("PSNR (dB)")
    ax_psnr.grid(True, alpha=0.3)
    ax_psnr.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


# ---------------------------------------------------------------------------------------------------
# Report


def fmt(value: float | None, pattern: str) -> str:
    return "n/a" if value is None or not math.isfinite(value) else pattern.format(value)


def metrics_table(initial: dict, trained: dict, random_init: dict | None = None) -> list[str]:
    """Metrics before and after training; with ``random_init`` (a warm-started run) the randomly initialised
    model first, and ``initial`` is the warm start."""
    if random_init is None:
        lines = ["| metric | untrained | trained | change |", "| --- | ---: | ---: | ---: |"]
    else:
        lines = ["| metric | random initialisation | warm start (step 0) | trained "
                 "| change from the warm start |",
                 "| --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for key, label, pattern, _ in METRIC_ROWS:
        a, b = initial["metrics"].get(key), trained["metrics"].get(key)
        change = fmt(b - a, "{:+" + pattern[2:]) if a is not None and b is not None else "n/a"
        first = "" if random_init is None else f" {fmt(random_init['metrics'].get(key), pattern)} |"
        lines.append(f"| {label} |{first} {fmt(a, pattern)} | {fmt(b, pattern)} | {change} |")
    return lines


def warm_start_section(
    random_init: dict, trained: dict, baselines: dict[str, float], weights: str
) -> list[str]:
    """What a warm-started demo run starts from, and the two goals of the demo against the yardsticks that
    need no training: PSNR over copying the mean of the context views, rotation error against the randomly
    initialised model's."""
    mean_copy = baselines.get(COPY_MEAN)
    rot0, rot1 = random_init["metrics"].get("rot_err_deg"), trained["metrics"].get("rot_err_deg")
    lines = [
        "## Where the pose-free run started",
        "",
        f"This run started from `{weights}` (`model.net.weights`), the small-scale stand-in for the pretrained "
        "3D foundation model the method builds on: `make warmstart` trains the same network on *other* "
        "synthetic scenes (another seed) with their cameras and a supervised camera loss "
        "(`conf/warmstart.yaml`). The training reported here is pose-free: it never saw a pose; poses "
        "served only to score it.",
        "",
    ]
    made = weights_provenance(weights)
    if made:
        lines += [made, ""]
    if mean_copy is not None:
        over = trained["metrics"]["psnr"] - mean_copy
        lines.append(f"- PSNR against copying the mean of the context views ({mean_copy:.2f} dB): "
                     f"{over:+.2f} dB (the demo's goal: at least {GOAL_DB_OVER_MEAN_COPY:+g} dB)")  # fmt: skip
    if rot0 and rot1 is not None and math.isfinite(rot0) and math.isfinite(rot1):
        lines.append(f"- rotation error against the randomly initialised model's ({rot0:.2f}°): {rot1:.2f}°, "
                     f"{rot1 / rot0:.2f}× (the demo's goal: at most {GOAL_ROTATION_RATIO:g}×)")  # fmt: skip
    return lines + [""]


def splat_section(
    initial: dict, trained: dict, transfer: dict | None, demo_goals: dict, start: str
) -> list[str]:
    """Whether the Gaussians form a scene or a point lattice: their opaque and sub-pixel shares and the fusion
    gain at step 0 and trained; the trained model's resolution transfer (``aesplat test
    --data.eval_transfer_scale 2``); each goal as ``goals`` judged it."""
    rows = [("opaque_share", "opacity above 0.99", "{:.1%}"),
            ("subpixel_share", "largest axis below 0.1 px in its own view", "{:.1%}"),
            ("fusion_gain_db", "fusion gain: all views − the best single view (dB)", "{:+.2f}")]  # fmt: skip
    lines = ["## The Gaussians: a scene, not a point lattice", "",
             f"| share of Gaussians, or figure | {start} (step 0) | trained |",
             "| --- | ---: | ---: |"]  # fmt: skip
    for key, label, pattern in rows:
        lines.append(f"| {label} | {fmt(initial['metrics'].get(key), pattern)} | "
                     f"{fmt(trained['metrics'].get(key), pattern)} |")  # fmt: skip
    lines.append("")
    if share := demo_goals.get("subpixel_share"):
        lines += [f"- sub-0.1-px share {share['value']:.1%} (the demo's goal: at most {share['goal']:.0%}; "
                  f"{_met(share)})"]  # fmt: skip
    if gain := demo_goals.get("transfer_gain_db"):
        metrics = transfer["metrics"]
        lines += [f"- rendered at twice the size ({metrics['psnr_transfer']:.2f} dB against the same scenes "
                  f"converted at twice the size) against the 1× render upsampled bilinearly "
                  f"({metrics['psnr_upsampled']:.2f} dB): **{gain['value']:+.2f} dB** (the demo's goal: "
                  f"at least {gain['goal']:+g} dB; {_met(gain)})"]  # fmt: skip
    return lines + ["", "A point lattice (Gaussians far below a pixel, all opaque, each seen only through the "
                    "rasterizer's 0.3-pixel low-pass) reproduces the pixels at the trained size and shows dots "
                    "at any other; docs/evaluation.md defines these figures.", ""]  # fmt: skip


def validation_samples(root: str | None) -> int:
    """Samples (one per scene) of the validation split of the shards under ``root``; 0 without one."""
    manifest = Path(root or "") / "manifest.json"
    if not manifest.is_file():
        return 0
    split = json.loads(manifest.read_text()).get("splits", {}).get("validation")
    return 0 if split is None else int(split.get("samples", 0))


def validated_scenes(samples: int, config: dict) -> int:
    """How many of ``samples`` validation scenes one validation pass of the run scored: all, unless the run's
    ``trainer.limit_val_batches`` (a number of batches of ``data.eval_batch_size``, or a fraction) cut it."""
    limit = config.get("trainer", {}).get("limit_val_batches")
    batch = int(config.get("data", {}).get("eval_batch_size") or 1)
    batches = math.ceil(samples / batch)
    if isinstance(limit, bool) or limit is None:
        return samples
    cut = int(limit) if isinstance(limit, int) else int(batches * float(limit))
    return min(samples, min(batches, cut) * batch)


def selection_section(
    metrics: list[dict[str, float]], trained: dict, samples: int, scored: int | None = None
) -> list[str]:
    """How the run's settings were chosen (on validation scenes, never on the test scenes), with the last
    validation figures of the run beside its test figures. ``samples``: scenes of the validation split (0:
    none); ``scored``: how many of them a validation pass scored (default: all)."""
    lines = ["## How this setting was chosen", ""]
    if not samples:
        return lines + [
            "These shards have **no validation split**: validation during training ran on the test scenes, so "
            "a checkpoint or setting picked on it would have seen them. Make one with `data_prep/synthetic.py "
            "--val-scenes N` or `data_prep/to_shards.py --val-scenes N` (docs/validation.md).",
            "",
        ]
    lines += [
        "The settings of `conf/demo.yaml` (its warm start and the pose-free learning rate) were chosen on "
        "*validation* scenes, a seed stream of their own, by their validation PSNR; the test scenes above "
        "played no part in any choice (docs/validation.md). During training, validation ran on the validation "
        "split; the test figures are of the last checkpoint.",
        "",
    ]
    val = [r for r in metrics if "val/psnr" in r and "step" in r]
    if val:
        last = val[-1]
        lines += [
            "| split | PSNR (dB) | rotation error (°) | translation error (°) |",
            "| --- | ---: | ---: | ---: |",
            f"| validation (step {int(last['step'])}, {samples if scored is None else scored} of {samples} "
            f"scenes) | {fmt(last.get('val/psnr'), '{:.2f}')} | "
            f"{fmt(last.get('val/rot_err_deg'), '{:.2f}')} | {fmt(last.get('val/trans_err_deg'), '{:.2f}')} |",
            f"| test (trained) | {fmt(trained['metrics'].get('psnr'), '{:.2f}')} | "
            f"{fmt(trained['metrics'].get('rot_err_deg'), '{:.2f}')} | "
            f"{fmt(trained['metrics'].get('trans_err_deg'), '{:.2f}')} |",
            "",
        ]
    return lines


def weights_provenance(weights: str) -> str:
    """How a weights file of scripts/export_weights.py was made (its note and training step), or ""."""
    path = Path(weights)
    if not path.is_file():
        return ""
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # noqa: BLE001 - a file this cannot read simply has no provenance to show
        return ""
    note = raw.get("note") if isinstance(raw, dict) else None
    if not note:
        return ""
    step = raw.get("global_step")
    return f"The weights file says how it was made: {note}" + (f", {step:,} training steps." if step else ".")


def bucket_table(initial: dict, trained: dict, start: str = "untrained") -> list[str]:
    lines = [f"| overlap bucket | scenes | {start} PSNR | trained PSNR |", "| --- | ---: | ---: | ---: |"]
    for bucket, values in trained.get("buckets", {}).items():
        before = initial.get("buckets", {}).get(bucket, {})
        lines.append(f"| {bucket} | {values.get('num_scenes', 0)} | {fmt(before.get('psnr'), '{:.2f}')} | "
                     f"{fmt(values.get('psnr'), '{:.2f}')} |")  # fmt: skip
    return lines


def posed_section(
    initial: dict,
    trained: dict,
    posed_initial: Path | None,
    posed_trained: Path | None,
    start: str = "untrained",
):
    """The diagnostic run with the data set's cameras next to the method's run (empty when it did not run)."""
    if posed_initial is None or posed_trained is None:
        return []
    if not ((posed_initial / "summary.json").is_file() and (posed_trained / "summary.json").is_file()):
        return ["(The posed diagnostic did not finish: no summary.json under "
                f"`{posed_initial}` and `{posed_trained}`.)", ""]  # fmt: skip
    posed0, posed1 = read_summary(posed_initial)["metrics"], read_summary(posed_trained)["metrics"]
    rows = [("predicted cameras (the method)", initial["metrics"], trained["metrics"]),
            ("the data set's cameras (`model.cameras: dataset`)", posed0, posed1)]  # fmt: skip
    lines = [
        "## Diagnostic: the same training with the data set's cameras",
        "",
        "`aesplat fit|test ... --model.cameras dataset` trains and tests the same model with the same "
        "settings, but with the data set's cameras (poses relative to context view 0, and intrinsics) in "
        "place of the camera head's. This is not the method (AESplat never sees a ground-truth pose in "
        "training); the gap between the two rows is what learning the cameras costs here. No pose is "
        "predicted in the second row, so none is scored (n/a).",
        "",
        f"| run | {start} PSNR | trained PSNR | gain | trained rotation error (°) "
        "| trained translation error (°) |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, before, after in rows:
        lines.append(
            f"| {name} | {before['psnr']:.2f} | {after['psnr']:.2f} | {after['psnr'] - before['psnr']:+.2f} | "
            f"{fmt(after.get('rot_err_deg'), '{:.2f}')} | {fmt(after.get('trans_err_deg'), '{:.1f}')} |"
        )
    method_gain = trained["metrics"]["psnr"] - initial["metrics"]["psnr"]
    if posed1["psnr"] - posed0["psnr"] > method_gain + 2.0:
        lines += ["", "With the cameras given, the depth and Gaussian heads learn far more in the same steps: "
                  "the pose head is what limits this run."]  # fmt: skip
    return lines + [""]


# ---------------------------------------------------------------------------------------------------
# The report's figures as data (demo.json): what the documentation pages quote


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _met(goal: dict) -> str:
    return "met" if goal["met"] else "NOT met"


def goals(
    trained: dict, random_init: dict | None, baselines: dict[str, float], transfer: dict | None = None
) -> dict:
    """The demo's goals, each with its measured value and whether it was met (absent if not measured)."""
    out = {}
    subpixel = _finite(trained["metrics"].get("subpixel_share"))
    if subpixel is not None:
        out["subpixel_share"] = {"goal": GOAL_MAX_SUBPIXEL_SHARE, "value": subpixel,
                                 "met": subpixel <= GOAL_MAX_SUBPIXEL_SHARE}  # fmt: skip
    gain = _finite(transfer["metrics"].get("transfer_gain_db")) if transfer else None
    if gain is not None:
        out["transfer_gain_db"] = {"goal": GOAL_MIN_TRANSFER_GAIN_DB, "value": gain,
                                   "met": gain >= GOAL_MIN_TRANSFER_GAIN_DB}  # fmt: skip
    mean_copy, psnr_ = baselines.get(COPY_MEAN), trained["metrics"].get("psnr")
    if mean_copy is not None and _finite(psnr_) is not None:
        over = psnr_ - mean_copy
        out["db_over_mean_copy"] = {"goal": GOAL_DB_OVER_MEAN_COPY, "value": over,
                                    "met": over >= GOAL_DB_OVER_MEAN_COPY}  # fmt: skip
    rot0 = _finite(random_init["metrics"].get("rot_err_deg")) if random_init else None
    rot1 = _finite(trained["metrics"].get("rot_err_deg"))
    if rot0 and rot1 is not None:
        out["rotation_ratio"] = {"goal": GOAL_ROTATION_RATIO, "value": rot1 / rot0,
                                 "met": rot1 / rot0 <= GOAL_ROTATION_RATIO}  # fmt: skip
    return out


HEADLINE_ROWS = [("psnr", "PSNR (dB) ↑", "{:.2f}", True), ("ssim", "SSIM ↑", "{:.3f}", False),
                 ("rot_err_deg", "rotation error (°) ↓", "{:.2f}", True),
                 ("trans_err_deg", "translation-direction error (°) ↓", "{:.1f}", False)]  # fmt: skip


def headline_table(results: dict) -> list[str]:
    """The demo's headline: the random initialisation (when the run started from weights), the model at step
    0 and the trained model on the test scenes, then the date, commit, machine and load of the run."""
    test, steps = results["test"], results["config"]["steps"]
    columns = [("random", "random initialisation")] if test.get("random") else []
    start = "warm start (step 0)" if results["config"].get("weights") else "untrained (step 0)"
    cameras = "pose-free " if results["config"].get("cameras") == "predicted" else ""
    columns += [("start", start), ("trained", f"trained, {steps} {cameras}steps")]
    lines = ["| metric | " + " | ".join(label for _, label in columns) + " |",
             "| --- |" + " ---: |" * len(columns)]  # fmt: skip
    for key, label, pattern, bold in HEADLINE_ROWS:
        cells = [fmt(test[name]["metrics"].get(key), pattern) for name, _ in columns]
        if bold:
            cells[-1] = f"**{cells[-1]}**"
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    m, load = results["machine"], results["load"]
    modified = " with local changes" if results.get("modified") else ""
    loads = " → ".join(f"{v[1]:.1f}" for v in (load.get("start"), load.get("end")) if v)
    when = results["date"][:16].replace("T", " ")
    return lines + [
        "",
        f"{test['scenes']} test scenes. `{results['command']}` on {when} UTC, "
        f"commit {results['commit']}{modified}; {m['cpu']}, {m['cores']} cores, torch {m['torch']}; "
        f"5-minute load average {loads or 'not known'} (start → end of the run).",
    ]


def write_results(results: dict, folder: Path, grid: Path | None = None) -> None:
    """demo.json, headline.md (and a copy of render_grid.png) into ``folder``, each whole or not at all."""
    write_whole(folder / "demo.json", (json.dumps(results, indent=1) + "\n").encode())
    write_whole(folder / "headline.md", ("\n".join(headline_table(results)) + "\n").encode())
    if grid is not None and grid.resolve() != (folder / grid.name).resolve():
        write_whole(folder / grid.name, grid.read_bytes())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, required=True, help="the `aesplat fit` run directory")
    parser.add_argument(
        "--initial", type=Path, required=True, help="`aesplat test` output of the untrained model"
    )
    parser.add_argument("--trained", type=Path, default=None, help="`aesplat test` output of the trained model "
                        "(default: RUN_DIR/test-latest)")  # fmt: skip
    parser.add_argument("--bench", type=Path, default=None, help="`aesplat bench` output folder, if it ran")
    parser.add_argument("--transfer", type=Path, default=None, help="`aesplat test --data.eval_transfer_scale "
                        "2` output of the trained model (the resolution-transfer figures)")  # fmt: skip
    parser.add_argument("--timings", type=Path, default=None, help="CSV stage,seconds written by `make demo`")
    parser.add_argument("--random-init", type=Path, default=None, help="`aesplat test --model.net.weights "
                        "null` output: the randomly initialised model (runs from weights)")  # fmt: skip
    parser.add_argument("--posed-initial", type=Path, default=None, help="`aesplat test --model.cameras "
                        "dataset` output of the untrained model (diagnostic, optional)")  # fmt: skip
    parser.add_argument("--posed-trained", type=Path, default=None, help="the same for the model trained with "
                        "`--model.cameras dataset`")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), help="report folder")
    parser.add_argument("--scenes", type=int, default=4, help="test scenes in the render grid")
    parser.add_argument("--results", type=Path, default=None, help="also write demo.json, headline.md and "
                        "render_grid.png here (docs/results/demo: what the documentation quotes)")  # fmt: skip
    parser.add_argument("--load-start", default=None, help="the load averages when the run started "
                        "('1.02 0.80 0.55', from /proc/loadavg)")  # fmt: skip
    parser.add_argument("--command", default="make demo", help="the command that ran, for demo.json")
    args = parser.parse_args(argv)
    load_start = [float(v) for v in args.load_start.split()[:3]] if args.load_start else None

    torch.set_grad_enabled(False)
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.device("cpu")
    initial = read_summary(args.initial)
    random_init = read_summary(args.random_init) if args.random_init else None
    trained = read_summary(args.trained or args.run_dir / "test-latest")
    transfer = read_summary(args.transfer) if args.transfer else None
    ckpt = find_checkpoint(args.run_dir)
    loaded = load_checkpoint(ckpt, device)
    config = run_config(ckpt)[0] or {}
    weights = config.get("model", {}).get("net", {}).get("weights")  # a warm start, when the run began from one
    start = "warm start" if weights else "untrained"
    metrics = read_metrics(args.run_dir)
    timings = read_timings(args.timings)

    # The render grid re-creates the untrained model from the run's seed; its PSNR must match `aesplat test`.
    all_scenes = evaluation_scenes(loaded, None, None, 1_000_000, device)  # every test scene, read once
    scenes = all_scenes[: args.scenes]
    untrained = initial_model(config, device)
    grid_psnr = render_grid(loaded, untrained, scenes, args.out / "render_grid.png", start)
    logged = read_per_scene(args.initial)
    recreated = [abs(v["untrained"] - logged[k]) for k, v in grid_psnr.items() if k in logged]
    recreated_ok = bool(recreated) and max(recreated) < 1e-2
    have_curve = loss_curve(metrics, initial["metrics"]["psnr"], trained["metrics"]["psnr"],
                            args.out / "loss_curve.png")  # fmt: skip

    baselines = context_copy_psnr([(scene.context.images, scene.target.images) for scene in all_scenes])
    demo_goals = goals(trained, random_init if weights else None, baselines, transfer)

    gain = trained["metrics"]["psnr"] - initial["metrics"]["psnr"]
    train_rows = [r for r in metrics if "train/loss" in r]
    steps = int(max((r["step"] for r in train_rows), default=-1)) + 1
    skipped = int(max((r.get("train/skipped_steps", 0) for r in train_rows), default=0))
    module = config.get("model", {})
    data, net, optim = config.get("data", {}), module.get("net", {}), module.get("optim", {})
    val_samples = validation_samples(data.get("root"))
    params = sum(p.numel() for p in loaded.model.parameters())
    lines = [
        "# aesplat demo report",
        "",
        f"Written {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC on {platform.machine()} "
        f"({torch.get_num_threads()} torch threads, torch {torch.__version__}, "
        f"Python {sys.version.split()[0]}). "
        "CPU only; wall times depend on the machine and on whatever else runs on it.",
        "",
        "## Result",
        "",
        f"Trained for {steps} steps, the model's test PSNR went from **{initial['metrics']['psnr']:.2f} dB** "
        + (f"(the warm start `{weights}`) " if weights else "(untrained, same seed and architecture) ")
        + f"to **{trained['metrics']['psnr']:.2f} dB**: "
        f"**{gain:+.2f} dB** on {trained['num_scenes']} held-out synthetic test scenes"
        + (" — visibly better." if gain >= 1.0 else "." if gain > 0 else " — no improvement (see below)."),
        "",
        *metrics_table(initial, trained, random_init if weights else None),
        "",
        "Image metrics are averaged per image over every target view of the test split, rendered with the "
        f"{CAMERAS[loaded.cameras]}; pose errors are angles against the ground-truth relative poses. "
        + (f"LPIPS: {trained['unavailable']['lpips']}." if trained.get("unavailable", {}).get("lpips") else ""),
        "",
        *bucket_table(initial, trained, start),
        "",
        "Copying context pixels needs no model; as a yardstick, such copies score on the same test scenes:",
        "",
        "| copy, no model | PSNR (dB) |",
        "| --- | ---: |",
        *[f"| {name} | {value:.2f} |" for name, value in baselines.items()],
        "",
        *(warm_start_section(random_init, trained, baselines, weights) if weights and random_init else []),
        *selection_section(metrics, trained, val_samples, validated_scenes(val_samples, config)),
        *splat_section(initial, trained, transfer, demo_goals, start),
        *posed_section(initial, trained, args.posed_initial, args.posed_trained, start),
        "## Setup",
        "",
        f"- model: `{net.get('size')}` ({params / 1e6:.2f} M parameters), "
        f"appearance `{net.get('appearance')}`, "
        f"SH degree {net.get('sh_degree')}, depth range {net.get('near')}–{net.get('far')}, "
        f"cameras `{loaded.cameras}` (`model.cameras`)",
        f"- data: synthetic scenes from `{data.get('root')}`, {data.get('image_size')}² px, "
        f"batch {data.get('batch_size')}, {data.get('num_context_views', 2)} context + "
        f"{data.get('num_target_views', 1)} target view(s) per training sample",
        f"- optimisation: AdamW lr {optim.get('lr')} (appearance {optim.get('appearance_lr')}), warm-up "
        f"{optim.get('warmup_steps')} steps then cosine; {skipped} step(s) skipped as non-finite",
        f"- checkpoint evaluated: `{ckpt}`; seed {config.get('seed_everything')}",
        "",
        "## Figures",
        "",
        "![render grid](render_grid.png)",
        "",
        f"`render_grid.png`: for each test scene, the two context views, the first target view, the {start} "
        "and trained renders of that view (PSNR over all the scene's target views underneath) and the "
        "trained model's rendered depth (near = warm).",
        "",
    ]
    if recreated:
        lines += [
            f"The {start} column re-creates the initial model from the run's seed"
            + (" and its weights" if weights else "")
            + "; its per-scene PSNR "
            f"{'matches' if recreated_ok else 'does NOT match'} `aesplat test` on that model "
            f"(largest difference {max(recreated):.2e} dB).",
            "",
        ]
    if have_curve:
        lines += ["![loss curve](loss_curve.png)", "",
                  "`loss_curve.png`: training loss and PSNR per step (light: raw, dark: moving average); "
                  "validation PSNR and the untrained/trained test PSNR marked.", ""]  # fmt: skip
    else:
        lines += ["(No loss curve: the run logged no metrics.csv — give `aesplat fit` a CSVLogger.)", ""]
    lines += timings_section(timings, steps)
    bench_md = args.bench / "BENCH.md" if args.bench else None
    if bench_md is not None and bench_md.is_file():
        body = bench_md.read_text().splitlines()[1:]  # its title becomes the section heading below
        body = ["#" + line if line.startswith("## ") else line for line in body]
        plot_path = Path(os.path.relpath(args.bench / "accuracy_vs_time.png", args.out))
        lines += ["## Accuracy versus time (`aesplat bench` on the trained checkpoint)", "",
                  f"![accuracy versus time]({plot_path.as_posix()})", "", *body]  # fmt: skip
    report = args.out / "REPORT.md"
    report.write_text("\n".join(lines) + "\n")

    val = [r for r in metrics if "val/psnr" in r and "step" in r]
    stage_seconds = {stage: s for stage, s in timings if not stage.startswith(WALL_CLOCK)}
    wall = [s for stage, s in timings if stage.startswith(WALL_CLOCK)]
    fit_seconds = stage_seconds.get("aesplat fit")
    validation = None
    if val:
        last = val[-1]
        scored = {k.removeprefix("val/"): v for k, v in last.items() if k.startswith("val/")}
        validation = {"step": int(last["step"]), "scenes": validated_scenes(val_samples, config),
                      "of": val_samples, **scored}  # fmt: skip
    posed = None
    if args.posed_initial and args.posed_trained and (args.posed_trained / "summary.json").is_file():
        posed = {"start": read_summary(args.posed_initial), "trained": read_summary(args.posed_trained)}
    results = {
        "command": args.command,
        **provenance(load_start),
        "config": {
            "steps": steps,
            "lr": optim.get("lr"),
            "appearance_lr": optim.get("appearance_lr"),
            "image_size": data.get("image_size"),
            "batch_size": data.get("batch_size"),
            "size": net.get("size"),
            "parameters": params,
            "weights": weights,
            "cameras": loaded.cameras,
            "seed": config.get("seed_everything"),
            "skipped_steps": skipped,
        },
        "test": {
            "scenes": trained["num_scenes"],
            "random": random_init if weights else None,
            "start": initial,
            "trained": trained,
            "transfer": transfer,
            "psnr_gain": gain,
        },
        "copy": {"mean": baselines.get(COPY_MEAN), "best": baselines.get(COPY_BEST)},
        "goals": demo_goals,
        "validation": validation,
        "posed": posed,
        "timings": {
            "stages": stage_seconds,
            "pipeline_seconds": wall[-1] if wall else None,
            "fit_seconds": fit_seconds,
            "seconds_per_step": fit_seconds / steps if fit_seconds and steps > 0 else None,
        },
    }
    write_results(results, args.out)
    if args.results is not None:
        write_results(results, args.results, args.out / "render_grid.png")
        print(f"demo_report: wrote {args.results / 'demo.json'}, headline.md and render_grid.png")
    print(f"demo_report: PSNR {initial['metrics']['psnr']:.2f} -> {trained['metrics']['psnr']:.2f} dB "
          f"({gain:+.2f} dB); wrote {report}, {args.out / 'render_grid.png'}"
          + (f", {args.out / 'loss_curve.png'}" if have_curve else ""))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
