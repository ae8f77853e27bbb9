"""The report of ``aesplat bench``: bench.csv, BENCH.md (a table per knob), accuracy_vs_time.png and bench.json,
with the machine the figures were measured on."""

from __future__ import annotations

import csv
import json
import math
import os
import platform
from collections.abc import Sequence
from dataclasses import asdict, fields
from pathlib import Path

import torch

from .run import Row
from .sweep import KNOB_TITLES

CSV_FIELDS = [f.name for f in fields(Row) if f.name != "setting"]  # the settings are in bench.json


def write_csv(rows: Sequence[Row], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: getattr(row, k) for k in CSV_FIELDS})


def markdown_tables(rows: Sequence[Row], meta: dict) -> str:
    """One markdown table per knob, with PSNR change and speed-up against the baseline."""
    base = next((r for r in rows if r.baseline and not r.skipped), None)
    lines = [
        "# Accuracy versus time",
        "",
        f"Checkpoint `{meta.get('ckpt', '?')}`, {meta.get('scenes', '?')} evaluation scenes, "
        f"{meta.get('device', '?')}, torch {meta.get('torch', '?')} with {meta.get('threads', '?')} threads; "
        f"median of {meta.get('repeats', '?')} repeats per scene after {meta.get('warmup', '?')} warm-up "
        f"run(s) per setting and {meta.get('process_warmup', 0)} of the baseline before the first. "
        "Milliseconds are per scene (model forward on context + target views, on the context views alone with "
        "the data set's cameras; rendering of the target views). "
        f"Cameras: {meta.get('cameras', 'predicted')} (`model.cameras`).",
        "",
    ]
    if base is not None:
        lines += [
            f"Baseline: every context view of a sample ({meta.get('context_views', '?')}), all SH bands, "
            f"{meta.get('native_size', '?')} px, all Gaussians, fp32, "
            f"`{base.setting.get('backend')}` backend — PSNR {base.psnr:.2f} dB, SSIM {base.ssim:.4f}, "
            f"{base.total_ms:.1f} ms ({base.forward_ms:.1f} forward + {base.render_ms:.1f} render).",
            "",
        ]
    for knob in dict.fromkeys(r.knob for r in rows):
        lines += [
            f"## {KNOB_TITLES.get(knob, knob)}",
            "",
            "| setting | PSNR (dB) | Δ PSNR | SSIM | rot. err (°) | forward ms | render ms | total ms "
            "| speed-up | Gaussians |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for r in (r for r in rows if r.knob == knob):
            label = f"**{r.label}**" if r.baseline else r.label
            if r.skipped:
                lines.append(f"| {label} | not measured here: {r.skipped} | | | | | | | | |")
                continue
            dpsnr = f"{r.psnr - base.psnr:+.2f}" if base else ""
            speed = f"{base.total_ms / r.total_ms:.2f}×" if base else ""
            rot = f"{r.rot_err_deg:.2f}" if math.isfinite(r.rot_err_deg) else "–"
            lines.append(
                f"| {label} | {r.psnr:.2f} | {dpsnr} | {r.ssim:.4f} | {rot} | {r.forward_ms:.1f} | "
                f"{r.render_ms:.1f} | {r.total_ms:.1f} | {speed} | {r.gaussians:,.0f} |"
            )
        lines.append("")
    lines.append("Bold: the baseline setting. Plot: `accuracy_vs_time.png`; raw figures: `bench.csv`.")
    return "\n".join(lines) + "\n"


def plot(rows: Sequence[Row], path: Path) -> None:
    """Quality against milliseconds: an overview (PSNR vs total ms, every knob), then one panel per knob
    (PSNR, and SSIM dashed on the right axis, vs total ms; points joined in the knob's own order)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    knobs = [k for k in dict.fromkeys(r.knob for r in rows) if any(r.knob == k and not r.skipped for r in rows)]
    cols = 3
    nrows = math.ceil((len(knobs) + 1) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.6 * cols, 4.2 * nrows), squeeze=False)
    flat = list(axes.flat)
    base = next((r for r in rows if r.baseline and not r.skipped), None)
    overview = flat[0]
    for i, knob in enumerate(knobs):
        pts = [r for r in rows if r.knob == knob and not r.skipped]
        xs, psnrs, ssims = [r.total_ms for r in pts], [r.psnr for r in pts], [r.ssim for r in pts]
        title = KNOB_TITLES.get(knob, knob)
        overview.plot(xs, psnrs, marker="o", color=f"C{i}", label=title, alpha=0.85)
        ax = flat[i + 1]
        ax.plot(xs, psnrs, marker="o", color=f"C{i}")
        for r, x, y in zip(pts, xs, psnrs):
            ax.annotate(r.label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        twin = ax.twinx()
        twin.plot(xs, ssims, marker="s", linestyle="--", color="0.5", alpha=0.7)
        twin.set_ylabel("SSIM (dashed)", color="0.4")
        _min_span(ax, psnrs, 1.0)  # flat series stay flat instead of magnifying 1e-6 dB differences
        _min_span(twin, ssims, 0.02)
        ax.set_title(title)
        ax.set_xlabel("total ms per scene")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(True, alpha=0.3)
    if base is not None:
        overview.scatter([base.total_ms], [base.psnr], marker="*", s=220, color="k", zorder=5, label="baseline")
    overview.set_xscale("log")
    overview.set_title("all knobs")
    overview.set_xlabel("total ms per scene (forward + render)")
    overview.set_ylabel("PSNR (dB)")
    overview.grid(True, which="both", alpha=0.3)
    overview.legend(fontsize=7, loc="best")
    for ax in flat[len(knobs) + 1 :]:
        ax.set_visible(False)
    fig.suptitle("aesplat: accuracy versus time (each knob varied alone from the baseline)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _min_span(ax, values: Sequence[float], span: float) -> None:
    """Give a y axis at least ``span`` of range around ``values``, without offset notation."""
    lo, hi = min(values), max(values)
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - 0.6 * span, mid + 0.6 * span)
    ax.ticklabel_format(axis="y", useOffset=False)


def write_report(rows: Sequence[Row], out_dir: str | Path, meta: dict) -> dict[str, Path]:
    """Write bench.csv, BENCH.md, accuracy_vs_time.png and bench.json under ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in ("bench.csv", "BENCH.md", "accuracy_vs_time.png", "bench.json")}
    write_csv(rows, paths["bench.csv"])
    paths["BENCH.md"].write_text(markdown_tables(rows, meta))
    plot(rows, paths["accuracy_vs_time.png"])
    paths["bench.json"].write_text(json.dumps({"meta": meta, "rows": [asdict(r) for r in rows]}, indent=1))
    return paths


def machine_meta(device: torch.device) -> dict:
    """Where the figures were measured."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = _cpu_name() or platform.processor() or platform.machine()
        name = f"{name}, {os.cpu_count()} logical cores"
    return {"device": f"{device.type} ({name})", "torch": torch.__version__, "threads": torch.get_num_threads()}


def _cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else an empty string."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        return ""
