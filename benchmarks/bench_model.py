"""Model benchmark: forward and forward+backward time and peak memory, split by module, on the CPU.

    python benchmarks/bench_model.py [--sizes tiny base] [--resolution 224] [--reps 3] [--warmup 1]

Workload: batch 1, 2 context + 1 target views, square images; the target is rendered with the predicted
target camera (torch backend). Every module is timed on its own with the inputs it received in a full
forward pass (inputs detached, float inputs requiring grad, backward of the mean of its outputs), so the
per-module figures add up to roughly the end-to-end ones. Peak memory is the peak of live tensor memory
allocated during the call (tracked op by op with a dispatch mode; parameters and inputs excluded), measured
in a separate run from the timings. Times are the fastest of --reps calls. Prints markdown.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import weakref
from collections.abc import Callable, Iterator

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from aesplat.model import build_model
from aesplat.render import render

MODULES = ("aggregator", "camera_head", "depth_head", "gaussian_head", "appearance")  # encoder in aggregator


class PeakTensorMemory(TorchDispatchMode):
    """Peak bytes of live tensor storage created inside the ``with`` block (CPU tensors)."""

    def __init__(self) -> None:
        super().__init__()
        self.live = 0
        self.peak = 0
        self._tracked: set[int] = set()

    def _free(self, key: int, nbytes: int) -> None:
        self.live -= nbytes
        self._tracked.discard(key)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor) and t.device.type == "cpu":
                storage = t.untyped_storage()
                key, nbytes = id(storage), storage.nbytes()
                if key in self._tracked or nbytes == 0:
                    continue
                self._tracked.add(key)
                self.live += nbytes
                self.peak = max(self.peak, self.live)
                weakref.finalize(storage, self._free, key, nbytes)
        return out


def _tensors(obj) -> list[torch.Tensor]:
    """Every tensor inside nested lists / tuples / dicts / dataclasses."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return [t for f in dataclasses.fields(obj) for t in _tensors(getattr(obj, f.name))]
    if isinstance(obj, (list, tuple)):
        return [t for x in obj for t in _tensors(x)]
    if isinstance(obj, dict):
        return [t for x in obj.values() for t in _tensors(x)]
    return []


def _fresh_inputs(obj, grad: bool):
    """Detached copies of the captured inputs; float tensors require grad when ``grad``."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach()
        return t.requires_grad_(grad and t.is_floating_point())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(
            obj, **{f.name: _fresh_inputs(getattr(obj, f.name), grad) for f in dataclasses.fields(obj)}
        )
    if isinstance(obj, (list, tuple)):
        return type(obj)(_fresh_inputs(x, grad) for x in obj)
    return obj


def _backward(out) -> None:
    loss = sum(t.float().mean() for t in _tensors(out) if t.requires_grad)
    loss.backward()


def _measure(fn: Callable[[], None], reps: int, warmup: int) -> tuple[float, float]:
    """(fastest of ``reps`` calls in milliseconds after ``warmup`` calls, peak tensor MiB of one extra call).

    The minimum, not the median: on a shared machine the other processes only ever add time."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - start))
    with PeakTensorMemory() as mem:
        fn()
    return min(times), mem.peak / 2**20


def bench_size(
    size: str, resolution: int, reps: int, warmup: int
) -> Iterator[tuple[str, float, float, float, float]]:
    torch.manual_seed(0)
    model = build_model(size, appearance="full", sh_degree=4)
    res = resolution
    ctx, tgt = torch.rand(1, 2, 3, res, res), torch.rand(1, 1, 3, res, res)

    captured: dict[str, tuple] = {}

    def capture(name: str):
        def hook(module, args, kwargs) -> None:
            captured[name] = (args, kwargs)

        return hook

    hooks = [getattr(model, n).register_forward_pre_hook(capture(n), with_kwargs=True) for n in MODULES]
    with torch.no_grad():
        out = model(ctx, tgt)
    for h in hooks:
        h.remove()
    render_inputs = (out.gaussians, out.extrinsics[:, 2:], out.intrinsics[:, 2:])

    def run_module(name: str, grad: bool) -> Callable[[], None]:
        args, kwargs = captured[name]

        def fn() -> None:
            a, k = _fresh_inputs(args, grad), {key: _fresh_inputs(v, grad) for key, v in kwargs.items()}
            with torch.set_grad_enabled(grad):
                result = getattr(model, name)(*a, **k)
                if grad:
                    _backward(result)

        return fn

    def run_render(grad: bool) -> Callable[[], None]:
        def fn() -> None:
            g, e, k = (_fresh_inputs(x, grad) for x in render_inputs)
            with torch.set_grad_enabled(grad):
                result = render(g, e, k, res, res, backend="torch")
                if grad:
                    _backward(result.color)

        return fn

    def run_all(grad: bool) -> Callable[[], None]:
        def fn() -> None:
            with torch.set_grad_enabled(grad):
                o = model(ctx, tgt)
                color = render(o.gaussians, o.extrinsics[:, 2:], o.intrinsics[:, 2:], res, res, backend="torch")
                if grad:
                    (color.color - tgt).square().mean().backward()

        return fn

    jobs = [(name, lambda g, n=name: run_module(n, g)) for name in MODULES] + [("render", run_render)]
    jobs.append(("**total** (model + render + loss)", run_all))
    for label, make in jobs:
        print(f"  measuring {size} {label} ...", file=sys.stderr, flush=True)
        fwd_ms, fwd_mib = _measure(make(False), reps, warmup)
        model.zero_grad(set_to_none=True)
        bwd_ms, bwd_mib = _measure(make(True), reps, warmup)
        model.zero_grad(set_to_none=True)
        yield label, fwd_ms, fwd_mib, bwd_ms, bwd_mib  # rows stream out as they are measured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["tiny", "base"])
    parser.add_argument("--resolution", type=int, default=224)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1, help="untimed calls before the timed ones")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    res = args.resolution
    print(f"torch {torch.__version__}, {args.threads} CPU threads, {res}² images, 2 context + 1 target views")
    for size in args.sizes:
        params = sum(p.numel() for p in build_model(size).parameters())
        print(f"\n### `{size}` ({params / 1e6:.1f} M parameters)\n")
        print("| module | forward ms | forward peak MiB | forward+backward ms | forward+backward peak MiB |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for label, fwd_ms, fwd_mib, bwd_ms, bwd_mib in bench_size(
            size, args.resolution, args.reps, args.warmup
        ):
            print(f"| {label} | {fwd_ms:.0f} | {fwd_mib:.0f} | {bwd_ms:.0f} | {bwd_mib:.0f} |", flush=True)


if __name__ == "__main__":
    main()
