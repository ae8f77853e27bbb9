"""Camera models of posed captures and their undistortion to a pinhole camera (docs/captures.md).

A :class:`Camera` holds pixel intrinsics and an OpenCV lens: the radial-tangential family (COLMAP's
``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV``; nerfstudio's ``OPENCV``) or the fisheye model
(``OPENCV_FISHEYE``, Kannala-Brandt). A distorted frame is undistorted by kornia to a pinhole image of the same
size and principal point, zoomed in only as far as needed to leave no blank pixel; a lens that cannot be
undistorted is refused. Pixel centres sit at (u + 0.5, v + 0.5), so ``cx / w`` is the normalised cx.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from .scene import SceneError

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
RADTAN_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")  # OpenCV's radial-tangential family
FISHEYE_MODELS = ("OPENCV_FISHEYE",)  # Kannala-Brandt, as OpenCV's fisheye module
SUPPORTED_MODELS = PINHOLE_MODELS + RADTAN_MODELS + FISHEYE_MODELS


@dataclass(frozen=True)
class Camera:
    """One source camera: pixel intrinsics for a ``width`` x ``height`` image and its lens model.

    ``distortion``: OpenCV coefficients, (k1, k2, p1, p2, k3, k4, k5, k6) for the radial-tangential models,
    (k1, k2, k3, k4) for ``OPENCV_FISHEYE``, empty for a pinhole camera."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @property
    def distorted(self) -> bool:
        return any(abs(c) > 0.0 for c in self.distortion)


def checked_camera(camera: Camera, what: str) -> Camera:
    """``camera`` if its intrinsics are finite with a positive focal length and size, else
    ``SceneError("bad_intrinsics")``."""
    values = (camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion)
    if not np.isfinite(values).all() or min(camera.fx, camera.fy, camera.width, camera.height) <= 0:
        raise SceneError(
            "bad_intrinsics",
            f"{what}: intrinsics must be finite with positive focal length and size, got fx={camera.fx}, "
            f"fy={camera.fy}, {camera.width}x{camera.height}",
        )
    return camera


def scaled_camera(camera: Camera, width: int, height: int, what: str) -> Camera:
    """The camera for an image of ``width`` x ``height`` read instead of its stated size: a uniform scale
    (down-scaled folders such as DL3DV's ``images_4``), else ``SceneError("image_size_mismatch")``."""
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) * max(camera.width, camera.height) > 1.0 + 1e-6 * camera.width:  # more than a pixel apart
        raise SceneError(
            "image_size_mismatch",
            f"{what}: the image is {width}x{height} but its camera says {camera.width}x{camera.height}, not a "
            "uniform down-scale; point --images at the folder the camera describes",
        )
    if (width, height) == (camera.width, camera.height):
        return camera
    return Camera(camera.model, width, height, camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy,
                  camera.distortion)  # fmt: skip


def normalized_intrinsics(camera: Camera) -> np.ndarray:
    """Pixel intrinsics -> normalised [3, 3] (fx, cx divided by the width, fy, cy by the height)."""
    return np.array([
        [camera.fx / camera.width, 0.0, camera.cx / camera.width],
        [0.0, camera.fy / camera.height, camera.cy / camera.height],
        [0.0, 0.0, 1.0],
    ])  # fmt: skip


def distorted_pixels(xy: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Points on the z = 1 plane [N, 2] -> where the distorted camera sees them, in pixels with integer pixel
    centres (kornia's convention; ours is shifted by 0.5) [N, 2]."""
    from kornia.geometry.calibration import distort_points
    from kornia.geometry.camera import distort_points_kannala_brandt

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx - 0.5, camera.cy - 0.5
    coeffs = torch.tensor(camera.distortion, dtype=xy.dtype)
    if camera.model in FISHEYE_MODELS:
        params = torch.cat([torch.tensor([fx, fy, cx, cy], dtype=xy.dtype), coeffs])
        return distort_points_kannala_brandt(xy, params.expand(len(xy), 8))
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=xy.dtype)
    dist = torch.zeros(8, dtype=xy.dtype)
    dist[: len(coeffs)] = coeffs
    return distort_points(xy, k, dist, new_K=torch.eye(3, dtype=xy.dtype))


def _plane_points(camera: Camera, zoom: float, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """Pixel centres (rows, cols broadcast) of the pinhole output camera zoomed by ``zoom`` -> z = 1 plane."""
    x = (cols + 0.5 - camera.cx) / (camera.fx * zoom)
    y = (rows + 0.5 - camera.cy) / (camera.fy * zoom)
    return torch.stack(torch.broadcast_tensors(x, y), dim=-1).reshape(-1, 2)


def undistortion_zoom(camera: Camera) -> float:
    """The smallest focal-length factor >= 1 for which every pixel of the pinhole output sees a pixel of the
    distorted image (its border is checked: the lens models are monotonic in the radius)."""
    w, h = camera.width, camera.height
    rows = torch.cat([torch.zeros(w), torch.full((w,), h - 1.0), torch.arange(h, dtype=torch.float64),
                      torch.arange(h, dtype=torch.float64)]).double()  # fmt: skip
    cols = torch.cat([torch.arange(w, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                      torch.zeros(h), torch.full((h,), w - 1.0)]).double()  # fmt: skip

    def inside(zoom: float) -> bool:
        uv = distorted_pixels(_plane_points(camera, zoom, rows, cols), camera)
        return bool(((uv >= 0) & (uv <= torch.tensor([w - 1.0, h - 1.0], dtype=uv.dtype))).all())

    if inside(1.0):
        return 1.0
    lo, hi = 1.0, 2.0
    while not inside(hi):
        lo, hi = hi, hi * 2.0
        if hi > 64.0:
            raise SceneError(
                "unsupported_distortion",
                f"the {camera.model} lens cannot be undistorted to a pinhole image without blank pixels; "
                "undistort it with COLMAP first",
            )
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return hi


def undistortion_map(camera: Camera, zoom: float) -> torch.Tensor:
    """For every pixel of the pinhole output (same size, same principal point, focal length ``zoom`` times the
    camera's), the source pixel it samples: float32 [H, W, 2] (x, y), integer pixel centres."""
    w, h = camera.width, camera.height
    rows = torch.arange(h, dtype=torch.float64)[:, None]
    cols = torch.arange(w, dtype=torch.float64)[None, :]
    return distorted_pixels(_plane_points(camera, zoom, rows, cols), camera).reshape(h, w, 2).float()


def undistort(image: Image.Image, camera: Camera, zoom: float, uv: torch.Tensor | None = None) -> Image.Image:
    """A distorted image (of ``camera``'s size) -> its pinhole image (see :func:`undistortion_map`, or pass the
    map as ``uv``), bilinearly resampled by kornia."""
    from kornia.geometry.transform import remap

    uv = undistortion_map(camera, zoom) if uv is None else uv
    pixels = torch.from_numpy(np.asarray(image.convert("RGB"), dtype=np.float32)).permute(2, 0, 1)[None]
    out = remap(pixels, uv[None, ..., 0], uv[None, ..., 1], mode="bilinear", align_corners=True)
    return Image.fromarray(out[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy())


def pinhole_camera(camera: Camera) -> tuple[Camera, float]:
    """The pinhole camera a frame is converted to, and the zoom of its undistortion (1 for a pinhole source)."""
    if not camera.distorted:
        return camera, 1.0
    zoom = undistortion_zoom(camera)
    return Camera("PINHOLE", camera.width, camera.height, camera.fx * zoom, camera.fy * zoom, camera.cx,
                  camera.cy), zoom  # fmt: skip
