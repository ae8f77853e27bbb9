"""The sweep of ``aesplat bench``: a ``Setting`` (a value for every knob), the ``Point``s of each knob's series,
and ``default_sweep``, every knob varied alone from the baseline."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

PRECISIONS = ("fp32", "bf16")  # of the model forward: float32, or bfloat16 autocast


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: a value for every knob. ``None`` sizes mean the data's own resolution."""

    sh_degree: int | None = None  # SH bands used at render time (None: all the model predicts)
    context_views: int | None = None  # context views fed to the model (None: every one the sample holds)
    input_size: int | None = None  # model input side, a multiple of the model's patch size
    render_size: int | None = None  # render side; upsampled to the data's side for the metrics
    keep_fraction: float = 1.0  # most opaque fraction of the Gaussians kept
    min_opacity: float = 0.0  # Gaussians below this opacity dropped
    precision: str = "fp32"  # "fp32" or "bf16" (autocast around the model forward)
    backend: str = "torch"  # renderer backend
    render_options: tuple[tuple[str, Any], ...] = ()  # extra keyword arguments of ``render``

    def forward_key(self) -> tuple:
        """Settings with the same key share the model forward (only rendering differs)."""
        return (self.context_views, self.input_size, self.precision)


@dataclass(frozen=True)
class Point:
    """A setting as one point of one knob's series."""

    knob: str  # the knob this series varies
    label: str  # its value in words, e.g. "SH 2", "112 px", "25 %"
    setting: Setting


def model_input_sizes(native: int, scales: Sequence[float], patch: int) -> list[int]:
    """Input sides for ``scales`` of the native side: multiples of ``patch`` (at least two), unique, sorted."""
    return sorted({max(2 * patch, round(native * s / patch) * patch) for s in scales} | {native})


def default_sweep(
    sh_degree: int,
    native_size: int,
    *,
    patch: int = 14,
    context_views: Sequence[int] = (2, 3, 4, 6),
    base_context_views: int | None = None,
    backends: Sequence[str] = ("torch",),
    input_scales: Sequence[float] = (0.5, 0.75, 1.0),
    render_scales: Sequence[float] = (0.25, 0.5, 0.75, 1.0),
    keep_fractions: Sequence[float] = (1.0, 0.5, 0.25, 0.1),
    min_opacities: Sequence[float] = (0.0, 0.05, 0.2, 0.5, 0.8),
    precisions: Sequence[str] = ("fp32", "bf16"),
    tile_sizes: Sequence[int] = (),
    base_tile_size: int | None = None,
    compiled: bool = False,
    knobs: Iterable[str] | None = None,
) -> tuple[Setting, list[Point]]:
    """Every knob swept alone from the baseline ``Setting(backend=backends[0])``; returns (baseline, points).

    patch: the model's patch size (input sides are multiples of it).
    context_views: counts of context views to feed the model; the baseline feeds every one a sample holds
    (``base_context_views`` when known: that count's point is the baseline itself, not measured again).

    tile_sizes: renderer tile sides to try (a speed-only knob: the image does not change); empty = skip.
    base_tile_size: the tile side the baseline renders with; that point is the baseline itself.
    compiled: add a "torch compiled" backend point (``render(..., compile=True)``).
    knobs: restrict to these knob names (default: all).
    """
    base = Setting(backend=backends[0])
    render_sizes = sorted({max(8, round(native_size * r)) for r in render_scales} | {native_size})

    def own(size: int) -> int | None:  # None stands for the data's own side
        return None if size == native_size else size

    def views(count: int) -> int | None:  # None stands for every view a sample holds
        return None if count == base_context_views else count

    def tile(side: int) -> tuple[tuple[str, Any], ...]:  # () stands for the baseline's own tile side
        return () if side == base_tile_size else (("tile_size", side),)

    series: dict[str, list[Point]] = {
        "sh_degree": [Point("sh_degree", f"SH {d}", replace(base, sh_degree=None if d == sh_degree else d))
                      for d in range(sh_degree + 1)],
        "context_views": [Point("context_views", f"{c} views", replace(base, context_views=views(c)))
                          for c in sorted(set(context_views))],
        "input_size": [Point("input_size", f"{s} px", replace(base, input_size=own(s)))
                       for s in model_input_sizes(native_size, input_scales, patch)],
        "render_size": [Point("render_size", f"{s} px", replace(base, render_size=own(s)))
                        for s in render_sizes],
        "keep_fraction": [Point("keep_fraction", f"{100 * f:g} %", replace(base, keep_fraction=f))
                          for f in sorted(set(keep_fractions) | {1.0})],
        "min_opacity": [Point("min_opacity", f"≥ {o:g}", replace(base, min_opacity=o))
                        for o in sorted(set(min_opacities) | {0.0})],
        "precision": [Point("precision", p, replace(base, precision=p)) for p in precisions],
        "backend": [Point("backend", b, replace(base, backend=b)) for b in backends],
        "tile_size": [Point("tile_size", f"tile {t}", replace(base, render_options=tile(t)))
                      for t in sorted(set(tile_sizes))],
    }  # fmt: skip
    if compiled:
        series["backend"].append(
            Point(
                "backend", "torch compiled", replace(base, backend="torch", render_options=(("compile", True),))
            )
        )
    chosen = list(series) if knobs is None else list(knobs)
    unknown = [k for k in chosen if k not in series]
    if unknown:
        raise ValueError(f"unknown knob(s) {unknown}; choose from {list(series)}")
    return base, [point for knob in chosen for point in series[knob]]


KNOB_TITLES = {
    "sh_degree": "SH degree at render",
    "context_views": "context views",
    "input_size": "model input resolution",
    "render_size": "render resolution",
    "keep_fraction": "Gaussians kept (most opaque)",
    "min_opacity": "Gaussians kept (opacity threshold)",
    "precision": "model precision",
    "backend": "renderer backend",
    "tile_size": "renderer tile size",
}
