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

from ..stats import interval_contains
from .run import Row
from .sweep import KNOB_TITLES
from .timing import Estimate, speed_verdict

CSV_FIELDS = [f.name for f in fields(Row) if f.name not in ("setting", "scene_psnr", "scene_ssim", "skipped")]
# bench.csv holds the measured rows; the settings, per-scene figures and skipped points are in bench.json


def write_csv(rows: Sequence[Row], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            if not row.skipped:
                writer.writerow({k: getattr(row, k) for k in CSV_FIELDS})


def _span(lo: float, hi: float, digits: int, signed: bool = False) -> str:
    fmt = f"{{:{'+' if signed else ''}.{digits}f}}"
    return f"{fmt.format(lo)} to {fmt.format(hi)}" if signed else f"{fmt.format(lo)}–{fmt.format(hi)}"


def with_interval(value: float, lo: float, hi: float, digits: int = 1) -> str:
    """``21.6 (21.2–22.0)``; the value alone when there is no interval."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} ({_span(lo, hi, digits)})"


def speedup_cell(row: Row) -> str:
    """The speed-up against the baseline as a ratio with its interval, or "no measurable difference"."""
    if row.baseline:
        return "baseline"
    verdict = speed_verdict(Estimate(row.speedup, row.speedup_lo, row.speedup_hi))
    if verdict == "untested":
        return f"{row.speedup:.2f}×, untested (fewer rounds than a 95 % interval needs)"
    span = f"{row.speedup_lo:.2f}–{row.speedup_hi:.2f}×"
    if verdict == "no measurable difference":
        return f"no measurable difference ({span})"
    return f"{row.speedup:.2f}× ({span})"


def change_cell(row: Row, metric: str, digits: int) -> str:
    """The change of ``metric`` (psnr, ssim) against the baseline with its interval over scenes, or "no
    measurable difference"."""
    if row.baseline:
        return "baseline"
    value, lo, hi = (getattr(row, f"{metric}_delta{end}") for end in ("", "_lo", "_hi"))
    if lo == hi == value:  # the same change in every scene (0: the same images)
        return "same images" if value == 0 else f"{value:+.{digits}f} in every scene"
    holds = interval_contains(lo, hi, 0.0)
    if holds is None:
        return f"{value:+.{digits}f}, untested (one scene)"
    if holds:
        return f"no measurable difference ({_span(lo, hi, digits, signed=True)})"
    return f"{value:+.{digits}f} ({_span(lo, hi, digits, signed=True)})"


def method(meta: dict) -> str:
    """How the figures were measured, in words."""
    get = meta.get
    return " ".join([
        f"Checkpoint `{get('ckpt', '?')}`, {get('scenes', '?')} evaluation scenes, {get('device', '?')},",
        f"torch {get('torch', '?')} with {get('threads', '?')} threads. Time: milliseconds per scene (model",
        "forward on context + target views, on the context views alone with the data set's cameras;",
        f"rendering of the target views), the median over {get('repeats', '?')} rounds, each of which times",
        f"every setting once (the baseline included) on {get('round_scenes', '?')} of the scenes (the next",
        "ones in turn each round), in an order rotated from round to round, after",
        f"{get('process_warmup', 0)} untimed baseline passes and one untimed pass of each",
        f"setting{_extra_warmup(meta)}; a cheap setting runs several times back to back per timing. Intervals:",
        "95 %; for times and speed-ups distribution-free, from order statistics over the rounds (a speed-up",
        "is the median of the per-round ratios baseline / setting, each taken within one round); for quality",
        "changes the Student-t interval of the mean per-scene difference from the baseline. An interval",
        'that holds no change reads "no measurable difference".',
        f"Memory: {get('allocator', 'the default allocator')}. Cameras: {get('cameras', 'predicted')}",
        "(`model.cameras`).",
    ])  # fmt: skip


def header(meta: dict, base: Row | None) -> list[str]:
    """What was measured, how, and under what load."""
    load = meta.get("load") or {}
    lines = ["# Accuracy versus time", "", method(meta), ""]
    if load:
        other = load.get("other_cores")
        busy = (
            "" if other is None else f"; other processes kept {other:.2f} of {load.get('cpu_count')} cores busy"
        )
        before, after = load.get("load_before") or [math.nan], load.get("load_after") or [math.nan]
        lines += [
            f"Load: 1-minute load average {before[0]:.2f} before, {after[0]:.2f} after{busy} "
            f"during the {load.get('seconds', '?')} s of measuring.",
            "",
        ]
    if meta.get("warning"):
        lines += [f"**{meta['warning']}**", ""]
    if base is not None:
        lines += [
            f"Baseline: every context view of a sample ({meta.get('context_views', '?')}), all SH bands, "
            f"{meta.get('native_size', '?')} px, all Gaussians, fp32, "
            f"`{base.setting.get('backend')}` backend — PSNR {base.psnr:.2f} dB, SSIM {base.ssim:.4f}, "
            f"{with_interval(base.total_ms, base.total_ms_lo, base.total_ms_hi)} ms "
            f"({base.forward_ms:.1f} forward + {base.render_ms:.1f} render).",
            "",
        ]
    return lines


def _extra_warmup(meta: dict) -> str:
    extra = meta.get("warmup", 0) or 0
    return f" and {extra} more untimed run(s) of each" if extra else ""


QUALITY_HEADER = ["| setting | PSNR (dB) | Δ PSNR (dB) | SSIM | Δ SSIM | rot. err (°) | Gaussians |",
                  "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
TIME_HEADER = [
    "| setting | forward ms | render ms | total ms | speed-up |",
    "| --- | ---: | ---: | ---: | ---: |",
]


def markdown_tables(rows: Sequence[Row], meta: dict) -> str:
    """Per knob of the measured points, a table of quality and one of time (each narrow enough for a page), with
    the changes against the baseline and their intervals; under them, one line naming the points that could
    not be measured here and why."""
    base = next((r for r in rows if r.baseline and not r.skipped), None)
    lines = header(meta, base)
    for knob in dict.fromkeys(r.knob for r in rows):
        measured = [r for r in rows if r.knob == knob and not r.skipped]
        quality, time = list(QUALITY_HEADER), list(TIME_HEADER)
        for r in measured:
            label = f"**{r.label}**" if r.baseline else r.label
            rot = f"{r.rot_err_deg:.2f}" if math.isfinite(r.rot_err_deg) else "–"
            ms = [with_interval(*(getattr(r, f"{name}_ms{end}") for end in ("", "_lo", "_hi")))
                  for name in ("forward", "render", "total")]  # fmt: skip
            quality.append(_row([label, f"{r.psnr:.2f}", change_cell(r, "psnr", 2), f"{r.ssim:.4f}",
                                 change_cell(r, "ssim", 4), rot, f"{r.gaussians:,.0f}"]))  # fmt: skip
            time.append(_row([label, *ms, speedup_cell(r)]))
        lines += [f"## {KNOB_TITLES.get(knob, knob)}", ""]
        if measured:
            lines += [*quality, "", *time, ""]
        skipped = [r for r in rows if r.knob == knob and r.skipped]
        if skipped:
            lines += ["Not measured here: " + "; ".join(f"{r.label} ({r.skipped})" for r in skipped) + ".", ""]
    lines.append("Bold: the baseline setting. Plot: `accuracy_vs_time.png`; raw figures: `bench.csv`.")
    return "\n".join(lines) + "\n"


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def plot(rows: Sequence[Row], path: Path) -> None:
    """Quality against milliseconds: an overview (PSNR vs total ms, every knob), then one panel per knob
    (PSNR, and SSIM dashed on the right axis, vs total ms; points joined in the knob's own order). Error bars:
    the 95 % intervals of the total time (across) and of the PSNR change from the baseline (up and down)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    measured = [r for r in rows if not r.skipped]
    knobs = list(dict.fromkeys(r.knob for r in measured))
    cols = 3
    nrows = math.ceil((len(knobs) + 1) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.6 * cols, 4.2 * nrows), squeeze=False)
    flat = list(axes.flat)
    base = next((r for r in measured if r.baseline), None)
    overview = flat[0]
    for i, knob in enumerate(knobs):
        pts = [r for r in measured if r.knob == knob]
        xs, psnrs, ssims = [r.total_ms for r in pts], [r.psnr for r in pts], [r.ssim for r in pts]
        xerr = [
            [_below(r.total_ms, r.total_ms_lo) for r in pts],
            [_above(r.total_ms, r.total_ms_hi) for r in pts],
        ]
        yerr = [[_below(r.psnr_delta, r.psnr_delta_lo) for r in pts],
                [_above(r.psnr_delta, r.psnr_delta_hi) for r in pts]]  # fmt: skip
        title = KNOB_TITLES.get(knob, knob)
        overview.errorbar(xs, psnrs, xerr=xerr, marker="o", color=f"C{i}", label=title, alpha=0.85, capsize=2)
        ax = flat[i + 1]
        ax.errorbar(xs, psnrs, xerr=xerr, yerr=yerr, marker="o", color=f"C{i}", capsize=3)
        for r, x, y in zip(pts, xs, psnrs):
            ax.annotate(r.label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        twin = ax.twinx()
        twin.plot(xs, ssims, marker="s", linestyle="--", color="0.5", alpha=0.7)
        twin.set_ylabel("SSIM (dashed)", color="0.4")
        _min_span(ax, psnrs, 1.0)  # flat series stay flat instead of magnifying 1e-6 dB differences
        _min_span(twin, ssims, 0.02)
        ax.set_title(title)
        ax.set_xlabel("total ms per scene (95 % interval)")
        ax.set_ylabel("PSNR (dB; bars: 95 % interval of the change)")
        ax.grid(True, alpha=0.3)
    if base is not None:
        overview.scatter([base.total_ms], [base.psnr], marker="*", s=220, color="k", zorder=5, label="baseline")
    overview.set_xscale("log")
    overview.set_title("all knobs")
    overview.set_xlabel("total ms per scene (forward + render; 95 % interval)")
    overview.set_ylabel("PSNR (dB)")
    overview.grid(True, which="both", alpha=0.3)
    overview.legend(fontsize=7, loc="best")
    for ax in flat[len(knobs) + 1 :]:
        ax.set_visible(False)
    fig.suptitle("aesplat: accuracy versus time (each knob varied alone from the baseline)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _below(value: float, lo: float) -> float:
    return value - lo if math.isfinite(lo) else 0.0


def _above(value: float, hi: float) -> float:
    return hi - value if math.isfinite(hi) else 0.0


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
