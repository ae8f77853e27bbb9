#!/usr/bin/env python
"""Point lattice or 3D scene: which scale parametrisation and rasterization mode make the demo's Gaussians a
scene that renders at any size, chosen on validation scenes over seeds.

    python benchmarks/splat_quality.py [--seeds 3] [--steps 600] [--warm-steps 8000] [--variants NAME ...]
        [--jobs 2] [--work outputs/splat_quality] [--out docs/results/splat_quality] [-- extra fit overrides]

1. Data, under --work: the demo's synthetic scenes (``data_prep/synthetic.py --val-scenes 12``), converted
   twice, at the demo's size (42) and at twice it (84, the ground truth of the resolution transfer); and the
   warm start's scenes, made as ``make warmstart`` makes them (``--warmstart-data``, shared with it).
2. A warm start per variant (``VARIANTS``): ``make warmstart``'s run (conf/demo.yaml + conf/warmstart.yaml,
   --warm-steps, one thread) with the variant's settings, so that no variant starts from Gaussian-head
   outputs learned under another; its weights file is written under --work/warmstarts. ``shipped`` takes the
   config's own warm start instead (the configuration as committed).
3. Runs: for each variant and seed (``seed_everything`` and ``data.seed``), --steps of ``aesplat fit -c
   conf/demo.yaml`` from the variant's warm start with its settings: the demo's pose-free training.
4. Evaluation of each run's last checkpoint on the VALIDATION scenes (``aesplat test --data.test_split
   validation``): at 42 px (PSNR, the opaque and sub-0.1-px shares, the fusion gain) and from the 84-px shards
   with ``--data.eval_transfer_scale 2`` (the resolution-transfer gain; train/splat_metrics.py).
5. Report, under --out: ``runs.csv`` (one line per run), ``results.json`` (per variant the mean and 95 %
   t-interval over seeds of every figure, the paired per-seed differences from ``absolute``, the choice and
   its rule; date, commit, machine, load) and ``table.md``.

The choice (``choose``): among the variants whose sub-0.1-px share is at most 10 % and whose transfer gain is
at least -0.5 dB (means over seeds), the highest validation PSNR. Test figures of the chosen setting come from
``make demo`` once it is the demo's default, never from here.

Run it again to resume: a finished warm start or run (its weights file, RUN/splat_quality.json, under the same
settings) is kept, an interrupted fit continues from its last checkpoint. ``--jobs 2`` trains two at once, one
thread each; ``--report-only`` rebuilds the report from the finished runs. The warm starts dominate: about 45
minutes each on one core.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from common import AESPLAT, demo_shards, provenance, t_interval, write_whole

REPO = Path(__file__).resolve().parents[1]

SIZE = 42
TRANSFER_SCALE = 2
# The demo's pixel at its median predicted depth is 0.094 scene units (focal length 1.03 x 42 px, depth
# ~4): a multiplier of 0.135 makes softplus(0) x multiplier that pixel at initialisation, where the paper's
# 0.001 (sized for 256-pixel scenes of another scale) starts at a 134th of it.
SIZED_MULTIPLIER = 0.135
VARIANTS: dict[str, dict[str, str]] = {
    "absolute": {"scale_mode": "absolute", "rasterize_mode": "classic"},
    "absolute_aa": {"scale_mode": "absolute", "rasterize_mode": "antialiased"},
    "sized_aa": {
        "scale_mode": "absolute",
        "scale_multiplier": str(SIZED_MULTIPLIER),
        "rasterize_mode": "antialiased",
    },  # fmt: skip
    "pixel": {"scale_mode": "pixel", "rasterize_mode": "classic"},
    "pixel_aa": {"scale_mode": "pixel", "rasterize_mode": "antialiased"},
    "shipped": {},  # the configuration as committed, from its own warm start file
}
NAMES = {
    "shipped": "the config as committed",
    "absolute": "absolute (0.001), classic",
    "absolute_aa": "absolute (0.001), antialiased",
    "sized_aa": f"absolute ({SIZED_MULTIPLIER}), antialiased",
    "pixel": "pixel (0.5–15 px), classic",
    "pixel_aa": "pixel (0.5–15 px), antialiased",
}
REFERENCE = "absolute"  # paired differences are taken from it: the same start, the paper's settings
FIGURES = ("psnr", "subpixel_share", "opaque_share", "fusion_gain_db", "transfer_gain_db", "psnr_transfer",
           "psnr_upsampled", "ssim", "rot_err_deg", "head_feature_rms", "scale_flat_share",
           "opacity_flat_share", "start_head_feature_rms", "start_scale_flat_share",
           "start_opacity_flat_share")  # fmt: skip
LABELS = {"psnr": "PSNR (dB)", "subpixel_share": "sub-0.1-px share", "opaque_share": "opacity > 0.99 share",
          "fusion_gain_db": "fusion gain (dB)", "transfer_gain_db": "transfer gain at 2× (dB)",
          "psnr_transfer": "PSNR at 2× (dB)", "psnr_upsampled": "1× upsampled, PSNR at 2× (dB)",
          "ssim": "SSIM", "rot_err_deg": "rotation error (°)", "head_feature_rms": "head feature RMS",
          "scale_flat_share": "flat scale outputs", "opacity_flat_share": "flat opacity outputs",
          "start_head_feature_rms": "warm start: head feature RMS",
          "start_scale_flat_share": "warm start: flat scale outputs",
          "start_opacity_flat_share": "warm start: flat opacity outputs"}  # fmt: skip
DIGITS = {"psnr": 2, "subpixel_share": 3, "opaque_share": 3, "fusion_gain_db": 2, "transfer_gain_db": 2,
          "psnr_transfer": 2, "psnr_upsampled": 2, "ssim": 3, "rot_err_deg": 2, "head_feature_rms": 1,
          "scale_flat_share": 3, "opacity_flat_share": 3, "start_head_feature_rms": 1,
          "start_scale_flat_share": 3, "start_opacity_flat_share": 3}  # fmt: skip
MAX_SUBPIXEL, MIN_TRANSFER = 0.10, -0.5  # the choice's admission rule


@dataclass(frozen=True)
class Settings:
    """What every run shares; recorded beside each run, whose results are reused only under the same."""

    config: str
    steps: int
    warm_steps: int
    extra: tuple[str, ...]


@dataclass(frozen=True)
class Run:
    variant: str
    seed: int

    def directory(self, work: Path) -> Path:
        return work / "runs" / self.variant / f"seed{self.seed}"


def prepare_data(work: Path) -> tuple[Path, Path]:
    """The demo's scenes, and their shards at the demo's size and at twice it (each made once)."""
    sizes = [(size, work / f"shards_{size}") for size in (SIZE, SIZE * TRANSFER_SCALE)]
    demo_shards(work / "src", sizes)
    return sizes[0][1], sizes[1][1]


def variant_args(variant: str) -> list[str]:
    """The ``aesplat fit`` overrides of a variant's settings."""
    options = {"scale_mode": "--model.net.options.scale_mode",
               "scale_multiplier": "--model.net.options.scale_multiplier",
               "rasterize_mode": "--model.render.options.rasterize_mode"}  # fmt: skip
    return [arg for key, value in VARIANTS[variant].items() for arg in (options[key], value)]


def warmstart_data(folder: Path) -> Path:
    """The warm start's shards, made as ``make warmstart`` makes them (once; the scene sources are removed)."""
    if not (folder / "manifest.json").exists():
        src = folder.parent / "src"
        scenes = ["--seed", "1", "--scenes", "1536", "--test-scenes", "8", "--threads", "2"]
        demo_shards(src, [(SIZE, folder)], scenes, ["--workers", "2"])
        shutil.rmtree(src)
    return folder


# Every command of the benchmark: no logger, no progress bar (its output goes to a log file), one thread.
QUIET = ("--trainer.logger", "false", "--trainer.enable_progress_bar", "false", "--threads", "1")


def _aesplat(args: list[str], log: Path) -> None:
    """``aesplat ARGS`` with ``QUIET``, its output appended to ``log``."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as f:
        subprocess.run([*AESPLAT, *args, *QUIET], check=True, stdout=f, stderr=subprocess.STDOUT)


def warm_start(variant: str, data: Path, work: Path, settings: Settings) -> Path:
    """The variant's warm start: ``make warmstart``'s fit with the variant's settings, one thread (resumed when
    interrupted), kept as a weights file; the config's own warm start for ``shipped``."""
    if not VARIANTS[variant]:
        import yaml

        return REPO / yaml.safe_load((REPO / settings.config).read_text())["model"]["net"]["weights"]
    out = work / "warmstarts" / f"{variant}-{settings.warm_steps}.pt"
    if out.exists():
        return out
    folder = work / "warmstarts" / f"{variant}-{settings.warm_steps}"
    print(f"splat_quality: {variant}: warm start ({settings.warm_steps} steps)", flush=True)
    _aesplat(["fit", "-c", str(REPO / settings.config), "-c", str(REPO / "conf/warmstart.yaml"), "--data.root",
              str(data), *variant_args(variant), "--trainer.max_steps", str(settings.warm_steps),
              "--trainer.default_root_dir", str(folder), "--ckpt_path", "last"],
             folder / "fit.log")  # fmt: skip
    note = (f"benchmarks/splat_quality.py: make warmstart's run with {' '.join(variant_args(variant))}, "
            f"{settings.warm_steps} steps")  # fmt: skip
    subprocess.run([sys.executable, str(REPO / "scripts/export_weights.py"), "--ckpt",
                    str(folder / "checkpoints" / "last.ckpt"), "--out", str(out), "--note", note],
                   check=True)  # fmt: skip
    return out


def warm_figures(variant: str, weights: Path, data: tuple[Path, Path], work: Path, settings: Settings) -> dict:
    """The warm start itself on the validation scenes (saved once beside its weights): rendered with the data
    set's cameras (``posed_*``: what the Gaussians can do, whatever the camera head learnt), and pose-free
    (``posefree_*``: where the demo's training starts, its rotation error included)."""
    path = work / "warmstarts" / f"{variant}-{settings.warm_steps}.json"
    if path.exists():
        return json.loads(path.read_text())["figures"]
    small, large = data
    folder = work / "warmstarts" / f"{variant}-{settings.warm_steps}-tests"
    base = ["test", "-c", str(REPO / settings.config), "--model.net.weights", str(weights),
            *variant_args(variant), "--data.test_split", "validation", "--data.image_size", str(SIZE),
            "--trainer.default_root_dir", str(folder)]  # fmt: skip
    summaries = {}
    for name, extra in (("posed", ["--model.cameras", "dataset", "--data.root", str(small)]),
                        ("posed_transfer", ["--model.cameras", "dataset", "--data.root", str(large),
                                            "--data.eval_transfer_scale", str(TRANSFER_SCALE)]),
                        ("posefree", ["--data.root", str(small)])):  # fmt: skip
        _aesplat([*base, *extra, "--model.eval.output_dir", str(folder / name)], folder / "test.log")
        summaries[name] = json.loads((folder / name / "test-latest" / "summary.json").read_text())["metrics"]
    figures = {f"posed_{m}": summaries["posed"][m] for m in ("psnr", "subpixel_share", "opaque_share",
                                                             "fusion_gain_db")}  # fmt: skip
    figures["posed_transfer_gain_db"] = summaries["posed_transfer"]["transfer_gain_db"]
    figures.update({f"posefree_{m}": summaries["posefree"][m] for m in ("psnr", "rot_err_deg")})
    write_whole(
        path, (json.dumps({"settings": asdict(settings), "figures": figures}, indent=1) + "\n").encode()
    )
    return figures


def fit(run: Run, weights: Path, shards: Path, work: Path, settings: Settings) -> None:
    """``aesplat fit`` of one run from its variant's warm start, one thread (continuing an interrupted one)."""
    folder = run.directory(work)
    _aesplat(["fit", "-c", str(REPO / settings.config), "--model.net.weights", str(weights),
              *variant_args(run.variant), "--seed_everything", str(run.seed), "--data.seed", str(run.seed),
              "--data.root", str(shards), "--data.image_size", str(SIZE), "--trainer.max_steps",
              str(settings.steps), "--trainer.default_root_dir", str(folder), *settings.extra, "--ckpt_path",
              "last"], folder / "fit.log")  # fmt: skip


def test(run: Run, shards: Path, work: Path, name: str, extra: list[str]) -> dict:
    """``aesplat test`` of the run's last checkpoint on the validation scenes; its summary's metrics."""
    folder = run.directory(work)
    out = folder / name
    _aesplat(["test", "-c", str(folder / "config.yaml"), "--data.root", str(shards), "--data.test_split",
              "validation", *extra, "--model.eval.output_dir", str(out), "--ckpt_path",
              str(folder / "checkpoints" / "last.ckpt")], folder / "test.log")  # fmt: skip
    return json.loads((out / "test-latest" / "summary.json").read_text())


# Where the head's activations stop passing gradients: a slope below 1e-4 of its largest, sigmoid(x) beyond
# |x| = 10.6 (the opacity, the pixel-mode scales), softplus(x) below x = -9.2 (the absolute-mode scales, which
# also stop at their cap, scale_max).
SIGMOID_FLAT, SOFTPLUS_FLAT = 10.6, -9.2


def head_statistics(model, shards: Path, cameras: str) -> dict:
    """What the Gaussian head's output layer sees and gives on the validation scenes: the RMS of its input
    features, and the shares of its scale and opacity outputs where the activation is flat (no gradient)."""
    import torch

    from aesplat.data import DataModule
    from aesplat.model import forward_batch

    data = DataModule(
        root=str(shards), image_size=SIZE, num_workers=0, eval_batch_size=1, test_split="validation"
    )
    seen: list[tuple] = []
    output = model.gaussian_head.scratch.output_conv2
    hook = output.register_forward_hook(lambda m, i, o: seen.append((i[0], o)))
    try:
        with torch.no_grad():
            for batch in data.eval_dataset("test"):
                forward_batch(model, batch.float_images(), cameras)
    finally:
        hook.remove()
    features = torch.cat([f.flatten(2) for f, _ in seen], dim=-1)  # [views, C, pixels]
    raw = torch.cat([o[:, 0:4].flatten(2) for _, o in seen], dim=-1)  # opacity, scale x3
    scales, opacity = raw[:, 1:4], raw[:, 0]
    if model.cfg.scale_mode == "pixel":
        flat_scales = scales.abs() > SIGMOID_FLAT
    else:  # flat below, and held by the cap above
        cap = model.cfg.scale_max <= model.cfg.scale_multiplier * torch.nn.functional.softplus(scales) + 1e-7
        flat_scales = (scales < SOFTPLUS_FLAT) | cap
    return {
        "head_feature_rms": float(features.pow(2).mean().sqrt()),
        "scale_flat_share": float(flat_scales.float().mean()),
        "opacity_flat_share": float((opacity.abs() > SIGMOID_FLAT).float().mean()),
    }


def run_head_statistics(run: Run, work: Path, shards: Path) -> dict:
    """``head_statistics`` of the run's warm start (``start_``) and of its trained checkpoint."""
    from omegaconf import OmegaConf

    from aesplat.checkpoint import load_checkpoint
    from aesplat.model import NetConfig

    folder = run.directory(work)
    loaded = load_checkpoint(folder / "checkpoints" / "last.ckpt")
    net = OmegaConf.to_container(OmegaConf.load(folder / "config.yaml"), resolve=True)["model"]["net"]
    start = NetConfig(**{**net, "compile": "none"}).build().eval()
    figures = head_statistics(loaded.model, shards, loaded.cameras)
    figures.update({f"start_{k}": v for k, v in head_statistics(start, shards, loaded.cameras).items()})
    return figures


def run_one(run: Run, weights: Path, data: tuple[Path, Path], work: Path, settings: Settings) -> dict:
    """Fit and evaluate one run; its figures (saved whole, which marks it finished)."""
    folder = run.directory(work)
    path = folder / "splat_quality.json"
    if path.exists():
        saved = json.loads(path.read_text())
        if saved["settings"] != json.loads(json.dumps(asdict(settings))):
            raise SystemExit(f"{folder} was made with other settings; delete it or use another --work")
        if not set(FIGURES) <= set(saved["figures"]):  # finished before these figures were kept
            tested = json.loads((folder / "test-42" / "test-latest" / "summary.json").read_text())["metrics"]
            saved["figures"]["rot_err_deg"] = tested["rot_err_deg"]
            saved["figures"].update(run_head_statistics(run, work, data[0]))
            write_whole(path, (json.dumps(saved, indent=1) + "\n").encode())
        return saved
    small, large = data
    print(f"splat_quality: {run.variant} seed {run.seed}: fit", flush=True)
    fit(run, weights, small, work, settings)
    at_size = test(run, small, work, "test-42", [])
    scale = ["--data.eval_transfer_scale", str(TRANSFER_SCALE), "--data.image_size", str(SIZE)]
    transfer = test(run, large, work, "test-transfer", scale)
    figures = {m: at_size["metrics"][m] for m in ("psnr", "ssim", "subpixel_share", "opaque_share",
                                                  "fusion_gain_db", "rot_err_deg")}  # fmt: skip
    figures.update({m: transfer["metrics"][m] for m in ("transfer_gain_db", "psnr_transfer", "psnr_upsampled")})
    figures.update(run_head_statistics(run, work, small))
    saved = {"settings": asdict(settings), "scenes": at_size["num_scenes"], "figures": figures}
    write_whole(path, (json.dumps(saved, indent=1) + "\n").encode())
    shown = ", ".join(f"{k} {v:.3f}" for k, v in figures.items())
    print(f"splat_quality: {run.variant} seed {run.seed}: {shown}", flush=True)
    return saved


# ----------------------------------------------------------------------------------------------- report


def summary(results: dict[Run, dict], variants: list[str]) -> list[dict]:
    """Per variant, the mean and 95 % t-interval over seeds of every figure; then, per variant, its paired
    per-seed difference from ``REFERENCE``."""
    seeds = sorted({run.seed for run in results})
    lines = []
    for variant in variants:
        found = [results[Run(variant, s)]["figures"] for s in seeds if Run(variant, s) in results]
        line: dict = {"id": variant, "variant": NAMES[variant], "n": len(found)}
        for m in FIGURES:
            line[m], line[f"{m}_ci"], _ = t_interval([f[m] for f in found])
        lines.append(line)
    lines += [x for v in variants if v != REFERENCE and (x := paired(results, v, REFERENCE))]
    return lines


def paired(results: dict[Run, dict], first: str, second: str) -> dict | None:
    """``first`` minus ``second``, seed by seed: the mean and 95 % t-interval of every figure (None without a
    seed that both ran)."""
    seeds = sorted({run.seed for run in results})
    pairs = [(results[Run(first, s)]["figures"], results[Run(second, s)]["figures"]) for s in seeds
             if Run(first, s) in results and Run(second, s) in results]  # fmt: skip
    if not pairs:
        return None
    line = {"id": f"{first}-{second}", "variant": f"{NAMES[first]} − {NAMES[second]}", "n": len(pairs)}
    for m in FIGURES:
        line[m], line[f"{m}_ci"], _ = t_interval([a[m] - b[m] for a, b in pairs])
    return line


def choose(lines: list[dict]) -> str | None:
    """The admitted candidate (sub-0.1-px share <= 10 %, transfer gain >= -0.5 dB) with the highest validation
    PSNR, or None when none is admitted. ``shipped`` is no candidate: it is what a choice was committed as."""
    admitted = [x for x in lines if x["id"] in VARIANTS and x["id"] != "shipped"
                and x["subpixel_share"] <= MAX_SUBPIXEL and x["transfer_gain_db"] >= MIN_TRANSFER]  # fmt: skip
    return max(admitted, key=lambda x: x["psnr"])["id"] if admitted else None


def _fmt(mean: float, half: float, digits: int) -> str:
    if not math.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f}" + (f" ± {half:.{digits}f}" if math.isfinite(half) else "")


# Tables of at most seven columns (the page's width): the warm starts in two, the runs' figures in two.
WARM_TABLES = (
    (("posed_psnr", "PSNR (dB)", 2), ("posed_transfer_gain_db", "transfer gain (dB)", 2),
     ("posed_fusion_gain_db", "fusion gain (dB)", 2), ("posed_subpixel_share", "sub-0.1-px share", 3),
     ("posed_opaque_share", "opacity > 0.99 share", 3)),
    (("posefree_psnr", "PSNR (dB)", 2), ("posefree_rot_err_deg", "rotation error (°)", 2)),
)  # fmt: skip
RUN_FIGURES = ("psnr", "rot_err_deg", "subpixel_share", "fusion_gain_db", "transfer_gain_db")
HEAD_FIGURES = ("opaque_share", "start_head_feature_rms", "head_feature_rms", "scale_flat_share",
                "opacity_flat_share")  # fmt: skip


def _table(rows: list[dict], figures: tuple[str, ...], title: str = "variant") -> list[str]:
    out = [f"| {title} | seeds | " + " | ".join(LABELS[m] for m in figures) + " |",
           "| --- | ---: |" + " ---: |" * len(figures)]  # fmt: skip
    for x in rows:
        cells = [_fmt(x[m], x[f"{m}_ci"], DIGITS[m]) for m in figures]
        out.append(f"| {x['variant']} | {x['n']} | " + " | ".join(cells) + " |")
    return out + [""]


def markdown(lines: list[dict], warm: dict[str, dict], chosen: str | None, meta: dict, settings: Settings,
             scenes: int) -> str:  # fmt: skip
    machine = meta["machine"]
    seeds = max(x["n"] for x in lines)
    out = [
        f"`python benchmarks/splat_quality.py --seeds {seeds}`: report {meta['date'][:16].replace('T', ' ')} "
        f"UTC at commit {meta['commit']}{' (modified)' if meta['modified'] else ''}; {machine['cpu']}, "
        f"{machine['cores']} cores, torch {machine.get('torch', '?')}. Per variant one warm start of "
        f"{settings.warm_steps:,} steps, then {settings.steps} pose-free steps of `{settings.config}` per "
        f"seed; {scenes} validation scenes at {SIZE}×{SIZE} (transfer: the same scenes' targets at "
        f"{SIZE * TRANSFER_SCALE}×{SIZE * TRANSFER_SCALE}). Mean ± half-width of the 95 % t-interval over "
        "seeds.",
        "",
        "**After the pose-free training** (the demo's pipeline):",
        "",
        *_table([x for x in lines if x["id"] in VARIANTS], RUN_FIGURES),
        f"**Paired by seed**: each variant minus {NAMES[REFERENCE]}, then the chosen variant minus each other "
        "admitted one:",
        "",
        *_table([x for x in lines if x["id"] not in VARIANTS], ("psnr", "rot_err_deg", "fusion_gain_db",
                                                                 "transfer_gain_db"), "difference"),
    ]  # fmt: skip
    titles = (
        "**The warm starts**, one per variant, at step 0, rendered with the data set's cameras (the camera "
        "head plays no part):",
        "**The warm starts**, pose-free at step 0 (where the demo's training starts):",
    )
    for title, columns in zip(titles, WARM_TABLES) if warm else ():
        out += [title, "", "| variant | " + " | ".join(label for _, label, _ in columns) + " |",
                "| --- |" + " ---: |" * len(columns)]  # fmt: skip
        for variant, figures in warm.items():
            cells = [_fmt(figures[m], math.nan, d) for m, _, d in columns]
            out.append(f"| {NAMES[variant]} | " + " | ".join(cells) + " |")
        out.append("")
    out += ["**The Gaussians and the Gaussian head** after the pose-free training: the opaque share, the RMS "
            "of the features entering the head's output layer (warm start, trained), and the shares of its "
            "scale and opacity outputs where the activation is flat, passing no gradient:", "",
            *_table([x for x in lines if x["id"] in VARIANTS], HEAD_FIGURES)]  # fmt: skip
    rule_text = (f"sub-0.1-px share ≤ {MAX_SUBPIXEL:.0%} and transfer gain ≥ {MIN_TRANSFER} dB, then the "
                 "highest validation PSNR")  # fmt: skip
    out.append(f"Chosen ({rule_text}): **{NAMES[chosen]}**." if chosen else f"No variant meets {rule_text}.")
    return "\n".join(out) + "\n"


def write_report(out: Path, results: dict[Run, dict], warm: dict[str, dict], variants: list[str],
                 settings: Settings, load_start: list[float]) -> None:  # fmt: skip
    import torch  # noqa: F401 - provenance() names the torch version of a process that imported it

    meta = provenance(load_start)
    columns = ["variant", "seed", *FIGURES]
    rows = [",".join(columns)]
    for run in sorted(results, key=lambda r: (variants.index(r.variant), r.seed)):
        values = {"variant": run.variant, "seed": run.seed, **results[run]["figures"]}
        rows.append(",".join(str(values[c]) for c in columns))
    write_whole(out / "runs.csv", ("\n".join(rows) + "\n").encode())
    lines = summary(results, variants)
    chosen = choose(lines)
    if chosen is not None:  # the chosen against every other admitted candidate, seed by seed
        others = [x["id"] for x in lines if x["id"] in VARIANTS and x["id"] not in (chosen, "shipped")
                  and x["subpixel_share"] <= MAX_SUBPIXEL
                  and x["transfer_gain_db"] >= MIN_TRANSFER]  # fmt: skip
        lines += [x for v in others if (x := paired(results, chosen, v))]
    scenes = next(iter(results.values()))["scenes"]
    clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in x.items()}
             for x in lines]  # fmt: skip
    record = {**meta, "settings": asdict(settings), "variants": {v: VARIANTS[v] for v in variants},
              "scenes": scenes, "rows": clean, "warm_starts": {v: warm[v] for v in variants if v in warm},
              "chosen": chosen,
              "rule": {"max_subpixel_share": MAX_SUBPIXEL, "min_transfer_gain_db": MIN_TRANSFER}}  # fmt: skip
    write_whole(out / "results.json", (json.dumps(record, indent=1) + "\n").encode())
    warm = {v: warm[v] for v in variants if v in warm}
    write_whole(out / "table.md", markdown(lines, warm, chosen, meta, settings, scenes).encode())
    print((out / "table.md").read_text())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--seeds", type=int, default=3, help="seeds per variant (default 3)")
    p.add_argument("--steps", type=int, default=600, help="training steps per run (default 600, the demo's)")
    p.add_argument(
        "--warm-steps", type=int, default=8000, help="warm-start steps (default 8000, make warmstart's)"
    )
    p.add_argument("--warmstart-data", type=Path, default=REPO / "outputs/warmstart/shards",
                   help="the warm start's shards (made as make warmstart makes them when missing)")  # fmt: skip
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--config", default="conf/demo.yaml")
    p.add_argument("--jobs", type=int, default=2, help="runs trained at once, one thread each (default 2)")
    p.add_argument("--work", type=Path, default=REPO / "outputs/splat_quality")
    p.add_argument("--out", type=Path, default=REPO / "docs/results/splat_quality")
    p.add_argument("--report-only", action="store_true", help="rebuild the report from the finished runs")
    p.add_argument("extra", nargs="*", help="after `--`: more `aesplat fit` overrides for every run")
    args = p.parse_args(argv)
    load_start = list(os.getloadavg())
    settings = Settings(args.config, args.steps, args.warm_steps, tuple(args.extra))
    runs = [Run(v, s) for s in range(args.seeds) for v in args.variants]
    results: dict[Run, dict] = {}
    warm_results: dict[str, dict] = {}
    if args.report_only:
        for variant in args.variants:
            path = args.work / "warmstarts" / f"{variant}-{settings.warm_steps}.json"
            if path.exists():
                warm_results[variant] = json.loads(path.read_text())["figures"]
        for run in runs:
            path = run.directory(args.work) / "splat_quality.json"
            if path.exists():
                results[run] = run_one(run, Path(), (args.work / f"shards_{SIZE}", Path()), args.work, settings)
    else:
        data = prepare_data(args.work)
        warm_data = warmstart_data(args.warmstart_data) if any(VARIANTS[v] for v in args.variants) else None
        with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            # The warm starts first; each variant's runs join the queue as its warm start is done.
            warm = {pool.submit(warm_start, v, warm_data, args.work, settings): v for v in args.variants}
            runs_of = {v: [run for run in runs if run.variant == v] for v in args.variants}
            pending: dict[concurrent.futures.Future, Run] = {}
            figures: dict[concurrent.futures.Future, str] = {}
            for future in concurrent.futures.as_completed(warm):
                weights, variant = future.result(), warm[future]
                figures[pool.submit(warm_figures, variant, weights, data, args.work, settings)] = variant
                for run in runs_of[variant]:
                    pending[pool.submit(run_one, run, weights, data, args.work, settings)] = run
            for future in concurrent.futures.as_completed(pending):
                results[pending[future]] = future.result()
            for future in concurrent.futures.as_completed(figures):
                warm_results[figures[future]] = future.result()
    if not results:
        raise SystemExit("splat_quality: no finished runs to report")
    write_report(args.out, results, warm_results, args.variants, settings, load_start)
    print(f"splat_quality: wrote {args.out}/runs.csv, results.json, table.md "
          f"({shlex.join(['--seeds', str(args.seeds)])})")  # fmt: skip


if __name__ == "__main__":
    main()
