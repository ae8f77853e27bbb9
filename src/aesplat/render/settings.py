"""Plain types of the rasterizer: the config section that picks it, the settings of a render (each marked with
the backends that read it) and the statistics a render returns.

They live apart from ``interface.py`` so that the interface and the backends both import them (and the
backends never import the interface that dispatches to them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from typing import Any

RASTERIZE_MODES = ("classic", "antialiased")


@dataclass(frozen=True)
class RenderSettings:
    """Options of ``render``, passed as keyword arguments. Each says who reads it: both backends, the torch
    backend only (the gsplat backend ignores it), or ``render`` itself before a backend runs.

    tile_size     both backends: screen tile side in pixels (torch backend: 8 or 16 are good; gsplat: 16)
    chunk         torch backend only: Gaussians per compositing step of each tile list
    max_elements  torch backend only: bound on tiles x pixels x chunk per step, its memory budget (about 60
                  bytes per element in the backward)
    step_elements  torch backend only: while fewer tiles are active than fill this many elements per step, the
                  step takes more of each list (chunk x 2^k): few long lists cost few steps (0: never)
    near, far     both backends: depth cull planes (camera z)
    eps2d         both backends: low-pass added to the 2D covariance
    rasterize_mode  both backends: "classic" (the low-pass widens a Gaussian, its opacity unchanged) or
                  "antialiased" (its opacity scaled by sqrt(det Σ / det(Σ + eps2d·I)), the Mip-Splatting 2D
                  filter: a Gaussian far below a pixel fades instead of passing for a whole pixel); gsplat's
                  names
    sh_tol        render itself: bands whose coefficients are all within this of zero are skipped
    compile       torch backend only: run the per-chunk maths through ``torch.compile`` (slow first call)
    """

    tile_size: int = 8
    chunk: int = 32
    max_elements: int = 1 << 22
    step_elements: int = 1 << 16
    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    rasterize_mode: str = "classic"
    sh_tol: float = 0.0
    compile: bool = False

    def __post_init__(self) -> None:
        if self.rasterize_mode not in RASTERIZE_MODES:
            raise ValueError(
                f"unknown rasterize_mode {self.rasterize_mode!r}; choose one of {', '.join(RASTERIZE_MODES)}"
            )
        if self.tile_size < 1 or self.chunk < 1 or self.max_elements < 1:
            raise ValueError(f"tile_size, chunk and max_elements must be positive: {self}")
        if not 0.0 < self.near < self.far:
            raise ValueError(f"need 0 < near < far, got near={self.near}, far={self.far}")


@dataclass
class RasterizerConfig:
    """The rasterizer a model renders with (config section ``model.render``): which backend, the background
    colour, and the ``RenderSettings`` (passed to ``render``)."""

    backend: str = "auto"  # auto | torch | gsplat
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    options: RenderSettings = field(default_factory=RenderSettings)  # tile_size, compile, ... (typed)

    def __post_init__(self) -> None:
        if isinstance(self.options, dict):  # as checkpoints store it: the fields that differ from the defaults
            known = {f.name for f in fields(RenderSettings)}
            if unknown := sorted(set(self.options) - known):
                raise ValueError(f"model.render.options: unknown key(s) {unknown}; known: {sorted(known)}")
            self.options = RenderSettings(**self.options)
        elif self.options is None:
            self.options = RenderSettings()

    def render_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``render`` for these settings (the background is the caller's: a tensor)."""
        return {"backend": self.backend, **asdict(self.options)}


class DeferredCount:
    """A count that lives on the device until it is read: ``int()``, ``==``, ``<`` or formatting read it once
    (on a GPU, that waits for the work queued before it), and nothing reads it otherwise."""

    def __init__(self, read: Callable[[], int]) -> None:
        self._read: Callable[[], int] | None = read
        self._value = 0

    def __int__(self) -> int:
        if self._read is not None:
            self._value, self._read = int(self._read()), None
        return self._value

    __index__ = __int__

    def __eq__(self, other: object) -> bool:
        return int(self) == other

    def __lt__(self, other: int) -> bool:
        return int(self) < other

    def __hash__(self) -> int:
        return hash(int(self))

    def __format__(self, spec: str) -> str:
        return format(int(self), spec)

    def __repr__(self) -> str:
        return repr(int(self)) if self._read is None else "DeferredCount(not read)"


@dataclass(frozen=True)
class RenderStats:
    """What a render call did: the "effects on demand" accounting.

    Counts are over (camera, Gaussian) pairs, in the order the culls run (a pair is counted once).
    """

    backend: str
    pairs: int  # B * V * N
    culled_transparent: int | DeferredCount  # opacity < 1/255 (the gsplat backend's is read when asked for)
    culled_depth: int  # behind the camera, at its centre, on or before the near plane, beyond far
    culled_footprint: int  # degenerate 2D covariance, or bounding box off the image
    visible: int  # pairs that reached sorting and compositing
    intersections: int  # (tile, Gaussian) pairs composited (torch backend; -1 where unknown)
    sh_degree_requested: int
    sh_degree_active: int  # bands actually evaluated (0: no SH basis at all)
