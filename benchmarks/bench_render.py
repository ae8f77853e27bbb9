"""Rasterizer benchmark: reference workload, scaling table, effects-on-demand savings, accuracy vs time.

    .venv/bin/python benchmarks/bench_render.py [--quick] [--repeats N] [--compile] [--backend torch]
        [--json docs/results/rasterizer/reference.json]

Prints markdown tables and writes ``docs/results/render_tradeoffs.png``. Uses 2 CPU threads. Timings are
medians over repeats; on a shared machine they are noisy, so compare rows from the same run. ``--json`` also
writes the reference workload's figures with the date, commit, machine and load (the file the documentation
quotes them from).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

# On a shared, oversubscribed machine, spinning OpenMP workers make 2-thread runs 10x slower; yield instead.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from bench_render_scene import reference_workload  # noqa: E402
from common import provenance, write_whole  # noqa: E402

from aesplat.render import render, render_with_stats  # noqa: E402
from aesplat.types import Gaussians  # noqa: E402

SIZE = 224


def _median_time(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _forward(g: Gaussians, ext, intr, size: int, **options) -> Callable[[], object]:
    def run():
        with torch.no_grad():
            return render(g, ext, intr, size, size, **options)

    return run


def _forward_backward(g: Gaussians, ext, intr, size: int, **options) -> Callable[[], object]:
    def run():
        leaves = g.apply(lambda t: t.detach().requires_grad_())
        e, i = ext.detach().requires_grad_(), intr.detach().requires_grad_()
        out = render(leaves, e, i, size, size, **options)
        (out.color.square().mean() + 0.1 * out.depth.mean() + out.alpha.mean()).backward()

    return run


def _psnr(x: torch.Tensor, ref: torch.Tensor) -> float:
    mse = F.mse_loss(x.clamp(0, 1), ref.clamp(0, 1)).item()
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def _fmt_psnr(p: float) -> str:
    return "exact" if math.isinf(p) else ("float round-off" if p > 100 else f"{p:.1f}")


def reference_section(repeats: int, compile_too: bool, options: dict) -> dict:
    """Print the reference workload's table; return its figures (milliseconds, GiB) for ``--json``."""
    g, ext, intr = reference_workload(SIZE)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    fwd = _median_time(_forward(g, ext, intr, SIZE, **options), repeats)
    fb = _median_time(_forward_backward(g, ext, intr, SIZE, **options), repeats)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    compiled = {**options, "compile": True}
    if compile_too:  # the first calls compile the kernels (minutes); the warm-up absorbs them
        cfwd = _median_time(_forward(g, ext, intr, SIZE, **compiled), repeats, warmup=2)
        cfb = _median_time(_forward_backward(g, ext, intr, SIZE, **compiled), repeats, warmup=2)
    _, stats = render_with_stats(g, ext, intr, SIZE, SIZE, **options)
    print("## Reference workload\n")
    print(
        f"2 views x {SIZE}^2 pixel-aligned Gaussians ({g.num_gaussians:,}), SH degree 4, one {SIZE}^2 target.\n"
    )
    print("| measure | value | goal |\n| --- | --- | --- |")
    print(f"| forward (median of {repeats}) | {fwd * 1e3:.0f} ms | <= 300 ms |")
    print(f"| forward + backward (median of {repeats}) | {fb * 1e3:.0f} ms | <= 800 ms |")
    if compile_too:
        print(f"| forward, `compile=True` (median of {repeats}) | {cfwd * 1e3:.0f} ms | <= 300 ms |")
        print(f"| forward + backward, `compile=True` (median of {repeats}) | {cfb * 1e3:.0f} ms | <= 800 ms |")
    print(f"| peak process memory (RSS; {rss0:.2f} GiB before the runs) | {rss:.2f} GiB | <= 2 GiB |")
    print(f"| visible / intersections | {stats.visible:,} / {stats.intersections:,} | |\n")
    figures = {"workload": {"gaussians": g.num_gaussians, "views": 2, "context_size": SIZE, "target_size": SIZE,
                            "sh_degree": 4}, "repeats": repeats, "forward_ms": fwd * 1e3,
               "forward_backward_ms": fb * 1e3, "peak_rss_gib": rss, "rss_before_gib": rss0,
               "visible": stats.visible, "intersections": stats.intersections}  # fmt: skip
    if compile_too:
        figures |= {"compiled_forward_ms": cfwd * 1e3, "compiled_forward_backward_ms": cfb * 1e3}
    return figures


def scaling_section(repeats: int, quick: bool, options: dict) -> None:
    print("## Scaling (forward / forward + backward, ms)\n")
    print("| case | Gaussians | image | SH | scale | forward | fwd + bwd |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rows = []
    sizes = [112, 224, 316] if quick else [112, 158, 224, 316, 448]
    for s in sizes:
        rows.append(("Gaussians", s, SIZE, 4, 1.0))
    for img in [112, 448] if quick else [112, 160, 320, 448]:
        rows.append(("image", SIZE, img, 4, 1.0))
    for deg in [0, 2] if quick else [0, 1, 2, 3]:
        rows.append(("SH degree", SIZE, SIZE, deg, 1.0))
    rows.append(("3x larger", SIZE, SIZE, 4, 3.0))
    # The CPU demo's scene (two 42^2 context views) into smaller and larger targets: the cost must not rise as
    # the image shrinks (few tiles with long lists; see render/composite.py).
    for img in [10, 42] if quick else [10, 21, 42, 84]:
        rows.append(("demo image", 42, img, 2, 1.0))
    for case, ctx, img, deg, scale in rows:
        g, ext, intr = reference_workload(ctx, sh_degree=deg, scale_factor=scale)
        fwd = _median_time(_forward(g, ext, intr, img, **options), repeats)
        fb = _median_time(_forward_backward(g, ext, intr, img, **options), repeats)
        shape = f"| {case} | {g.num_gaussians:,} | {img}^2 | {deg} | {scale:g}x"
        print(f"{shape} | {fwd * 1e3:.0f} | {fb * 1e3:.0f} |")
    print()


def effects_section(repeats: int, options: dict) -> None:
    """What culling and active-degree skipping save."""
    g, ext, intr = reference_workload(SIZE)
    sh = g.sh.clone()
    sh[:, :, 1:] = 0.0  # an I2DC-only scene stored with degree-4 coefficients
    flat = Gaussians(g.means, g.quats, g.scales, g.opacities, sh)
    skip = _median_time(_forward(flat, ext, intr, SIZE, **options), repeats)
    full = _median_time(_forward(flat, ext, intr, SIZE, sh_tol=-1.0, **options), repeats)
    # Double the scene with Gaussians the renderer must reject: half behind the camera, half transparent.
    n = g.num_gaussians
    behind = g.means.clone()
    behind[..., 2] = -behind[..., 2]
    junk_opacity = torch.cat([torch.ones(1, n // 2), torch.full((1, n - n // 2), 1e-3)], dim=1)
    opac = torch.cat([g.opacities, torch.where(junk_opacity > 0.5, g.opacities, junk_opacity)], dim=1)
    means = torch.cat([g.means, torch.where(junk_opacity[..., None] > 0.5, behind, g.means)], dim=1)
    doubled = Gaussians(means, g.quats.repeat(1, 2, 1), g.scales.repeat(1, 2, 1), opac, g.sh.repeat(1, 2, 1, 1))
    base = _median_time(_forward(g, ext, intr, SIZE, **options), repeats)
    with_junk = _median_time(_forward(doubled, ext, intr, SIZE, **options), repeats)
    _, st = render_with_stats(doubled, ext, intr, SIZE, SIZE, **options)
    print("## Effects on demand (forward, ms)\n")
    print("| scene | evaluated | time |\n| --- | --- | --- |")
    print(f"| degree-4 SH storage, bands 1-4 silent | active degree 0 (no SH basis) | {skip * 1e3:.0f} |")
    print(f"| same, skipping disabled (`sh_tol=-1`) | degree 4 | {full * 1e3:.0f} |")
    print(f"| reference workload | {n:,} Gaussians | {base * 1e3:.0f} |")
    print(
        f"| + {n:,} rejected Gaussians | culled: {st.culled_depth:,} behind camera, {st.culled_transparent:,} "
        f"transparent, {st.culled_footprint:,} off-screen/degenerate | {with_junk * 1e3:.0f} |\n"
    )


def tradeoff_section(repeats: int, compile_too: bool, out_png: Path, options: dict) -> None:
    """PSNR against the full-quality render versus forward time, one series per quality knob."""
    g, ext, intr = reference_workload(SIZE)
    with torch.no_grad():
        ref = render(g, ext, intr, SIZE, SIZE, **options).color[0, 0]
    series: dict[str, list[tuple[str, float, float]]] = {}

    def measure(knob: str, label: str, fn: Callable[[], torch.Tensor]) -> None:
        t = _median_time(fn, repeats)
        series.setdefault(knob, []).append((label, t * 1e3, _psnr(fn(), ref)))

    def colour(size: int = SIZE, **extra) -> Callable[[], torch.Tensor]:
        def run() -> torch.Tensor:
            with torch.no_grad():
                img = render(g, ext, intr, size, size, **{**options, **extra}).color[0]
            if size != SIZE:
                img = F.interpolate(img, size=(SIZE, SIZE), mode="bilinear", align_corners=False)
            return img[0]

        return run

    for deg in range(5):
        measure("SH degree", f"L={deg}", colour(sh_degree=deg))
    for res in (112, 160, 224):
        measure("resolution (upsampled)", f"{res}px", colour(res))
    for ts in (4, 8, 16):
        measure("tile size", f"{ts}px", colour(tile_size=ts))
    for chunk in (16, 32, 64):
        measure("chunk", f"{chunk}", colour(chunk=chunk))
    if compile_too:
        for comp in (False, True):
            measure("torch.compile", "compiled" if comp else "eager", colour(compile=comp))

    print("## Accuracy versus time (forward)\n")
    print("PSNR (dB) against the full-quality render (SH 4, 224^2, default tiling); `exact` = identical.\n")
    print("| knob | setting | forward ms | PSNR |\n| --- | --- | --- | --- |")
    for knob, points in series.items():
        for label, ms, psnr in points:
            print(f"| {knob} | {label} | {ms:.0f} | {_fmt_psnr(psnr)} |")
    print()
    _plot(series, out_png)
    print(f"Plot: `{out_png}`\n")


def _plot(series: dict[str, list[tuple[str, float, float]]], out_png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cap = 60.0  # identical up to float round-off (or exactly): drawn at the top of the axis
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for knob, points in series.items():
        xs = [ms for _, ms, _ in points]
        ys = [min(p, cap) for _, _, p in points]
        ax.plot(xs, ys, marker="o", label=knob)
        for (label, _, _), x, y in zip(points, xs, ys):
            ax.annotate(label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlabel(f"forward time (ms, {torch.get_num_threads()} CPU threads, shared machine)")
    ax.set_ylabel(f"PSNR vs full quality (dB; >= {cap:g} drawn at {cap:g})")
    ax.set_title("Rasterizer quality knobs: accuracy versus time")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer rows and repeats (a smoke run)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per row (default 5, quick 1)")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile'd kernels (slow start)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    parser.add_argument("--backend", default="torch", help="render backend to time (torch, gsplat, auto)")
    parser.add_argument(
        "--tile-size", type=int, default=None, help="tile size for all rows (default: renderer's)"
    )
    parser.add_argument(
        "--sections", default="reference,effects,scaling,tradeoffs", help="comma-separated subset"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "docs" / "results" / "render_tradeoffs.png",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the reference workload's "
                        "figures, date, commit, machine and load to this file")  # fmt: skip
    args = parser.parse_args()
    load_start = list(os.getloadavg())
    torch.set_num_threads(args.threads)
    repeats = args.repeats or (1 if args.quick else 5)
    options = {"backend": args.backend}
    if args.tile_size:
        options["tile_size"] = args.tile_size
    mode = " (quick)" if args.quick else ""
    omp = os.environ["OMP_WAIT_POLICY"]
    print(f"# Rasterizer benchmark\n\ntorch {torch.__version__}, {torch.get_num_threads()} threads "
          f"(OMP_WAIT_POLICY={omp}), backend {args.backend}, repeats {repeats}{mode}. "
          "The machine is shared: timings are noisy.\n")  # fmt: skip
    sections = args.sections.split(",")
    if "reference" in sections:
        reference = reference_section(repeats, args.compile, options)
        if args.json is not None:
            command = "python benchmarks/bench_render.py " + " ".join(sys.argv[1:])
            record = {"command": command.strip(), **provenance([round(v, 2) for v in load_start]),
                      "backend": args.backend, "threads": torch.get_num_threads(), **reference}  # fmt: skip
            write_whole(args.json, (json.dumps(record, indent=1) + "\n").encode())
            print(f"Reference workload figures: `{args.json}`\n")
    if "effects" in sections:
        effects_section(repeats, options)
    if "scaling" in sections:
        scaling_section(repeats, args.quick, options)
    if "tradeoffs" in sections:
        tradeoff_section(repeats, args.compile, args.out, options)


if __name__ == "__main__":
    main()
