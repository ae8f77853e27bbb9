"""The gsplat backend's own cost: ``render(backend="gsplat")`` versus calling ``gsplat.rasterization`` directly.

    python benchmarks/bench_gsplat_overhead.py [--batch 10] [--repeats 20]    # needs CUDA and gsplat

Workloads (forward + backward, CUDA-synchronised, median of the repeats after warm-up):
  - one training batch: ``--batch`` scenes of 2 × 224² pixel-aligned Gaussians (SH degree 4) -> one 224²
    target each;
  - the reference workload: 100,352 Gaussians -> one 224² target.
The direct call gets the same Gaussians in world space with a rigid view matrix and real K (no gradient for
K); ``render`` also differentiates the cameras, intrinsics included. The goal is ≤ 1.5× the direct
call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from bench_render_scene import reference_workload  # noqa: E402

from aesplat.geometry import invert_pose  # noqa: E402
from aesplat.render import gsplat_available, render  # noqa: E402
from aesplat.types import Gaussians  # noqa: E402

SIZE = 224


def _median_ms(fn, leaves, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn(leaves)
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(leaves)
        torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def _workload(batch: int) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    """``batch`` copies of the reference scene with their target camera, on the GPU, as leaves."""
    g, ext, intr = reference_workload(SIZE, sh_degree=4)
    fields = (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)
    tensors = [t.expand(batch, *t.shape[1:]).contiguous().cuda() for t in fields]
    return tuple(t.requires_grad_() for t in tensors)  # type: ignore[return-value]


def _through_render(leaves) -> None:
    means, quats, scales, opacities, sh, ext, intr = leaves
    out = render(Gaussians(means, quats, scales, opacities, sh), ext, intr, SIZE, SIZE, backend="gsplat")
    (out.color.sum() + out.depth.sum()).backward()


def _direct(leaves) -> None:
    import gsplat

    means, quats, scales, opacities, sh, ext, intr = leaves
    b = means.shape[0]
    pixels = intr.new_tensor([SIZE, SIZE, 1.0])[:, None]
    colors, _, _ = gsplat.rasterization(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=sh, sh_degree=4,
        viewmats=invert_pose(ext), Ks=(intr * pixels).detach(), width=SIZE, height=SIZE,
        backgrounds=torch.zeros(b, 1, 3, device=means.device), render_mode="RGB+ED", packed=False,
    )  # fmt: skip
    colors.sum().backward()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=10, help="scenes per training batch (default 10)")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    if not gsplat_available():
        raise SystemExit("this benchmark needs CUDA and gsplat (pip install 'gsplat>=1.5')")
    import gsplat

    print(f"torch {torch.__version__}, gsplat {gsplat.__version__}, {torch.cuda.get_device_name()}")
    print("| workload | render(backend='gsplat') | gsplat.rasterization | ratio |")
    print("| --- | --- | --- | --- |")
    workloads = ((f"training batch ({args.batch} × 2 × 224² -> 224²)", args.batch), ("reference (1 scene)", 1))
    for name, batch in workloads:
        leaves = _workload(batch)
        ours = _median_ms(_through_render, leaves, args.repeats)
        raw = _median_ms(_direct, leaves, args.repeats)
        print(f"| {name} | {ours:.2f} ms | {raw:.2f} ms | {ours / raw:.2f}× |")


if __name__ == "__main__":
    main()
