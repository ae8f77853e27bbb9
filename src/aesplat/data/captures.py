"""Posed captures: a nerfstudio ``transforms.json`` or a COLMAP sparse model -> cameras in this project's
convention (camera-to-world, OpenCV axes, normalised pinhole intrinsics) and the frames' images.

Conventions of the sources, and what is done with them:

- nerfstudio: ``transform_matrix`` is camera-to-world with OpenGL / Blender camera axes (x right, y up,
  z backward), so its y and z columns are negated. An ``applied_transform`` (the 3x4 world transform
  ``ns-process-data`` applied to the original poses) is undone, so the world frame is the capture's own.
  Intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, distortion) sit at the top level or per frame
  (a frame's value wins). ``file_path`` is relative to the JSON file.
- COLMAP: each image holds a world-to-camera rotation (unit quaternion w, x, y, z) and translation in OpenCV
  axes; ``cameras`` hold the pixel intrinsics. Text (``*.txt``) and binary (``*.bin``, little endian, the
  layout documented at https://colmap.github.io/format.html) models are read; ``points3D`` is not needed.
- Both put pixel centres at (u + 0.5, v + 0.5), as this project does, so ``cx / w`` is the normalised cx.

Intrinsics are normalised by the camera's stated size, so a uniformly down-scaled image folder (DL3DV's
``images_4``) keeps them; an image whose size is not a uniform scale of the stated one is refused.
Distorted cameras are undistorted to a pinhole camera with the same focal length and principal point (zoomed in
only as far as needed to leave no blank pixel) by kornia; a model that cannot be undistorted is refused.
Every refusal is a :class:`CaptureError` carrying a short reason code and a one-line message.
"""

from __future__ import annotations

import io
import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

FORMATS = ("nerfstudio", "colmap")
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z: OpenGL / Blender axes <-> OpenCV axes
RIGID_TOL = 1e-3  # |R^T R - I| and |det R - 1| allowed in a stored pose (text files keep ~7 digits)

# COLMAP camera models: id -> (name, parameter names). Pinhole models need no undistortion.
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k1")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
}
COLMAP_MODEL_IDS = {name: i for i, (name, _) in COLMAP_MODELS.items()}
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
RADTAN_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")  # OpenCV's radial-tangential family
FISHEYE_MODELS = ("OPENCV_FISHEYE",)  # Kannala-Brandt, as OpenCV's fisheye module
SUPPORTED_MODELS = PINHOLE_MODELS + RADTAN_MODELS + FISHEYE_MODELS


class CaptureError(ValueError):
    """A scene that cannot be converted: ``reason`` is a short code (counted in the manifest), the message one
    line naming the problem and the fix."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


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


@dataclass
class Capture:
    """A posed capture's frames in this project's convention, in frame order.

    c2w float64 [F, 4, 4] camera-to-world (OpenCV axes, the capture's world frame); cameras: one per frame;
    paths: the image files; names: the frames' names (the sort key)."""

    key: str
    names: list[str]
    paths: list[Path]
    c2w: np.ndarray
    cameras: list[Camera]

    def __len__(self) -> int:
        return len(self.paths)


# ----------------------------------------------------------------------------------------------- poses


def check_rigid(c2w: np.ndarray, what: str) -> None:
    """Raise ``CaptureError("bad_pose")`` unless ``c2w`` [4, 4] is finite with a rotation (orthonormal, det 1)
    and a last row (0, 0, 0, 1)."""
    if not np.isfinite(c2w).all():
        raise CaptureError("bad_pose", f"{what}: the pose holds NaN or Inf; fix or drop the frame")
    rot = c2w[:3, :3]
    err = max(np.abs(rot.T @ rot - np.eye(3)).max(), abs(np.linalg.det(rot) - 1.0))
    if err > RIGID_TOL or not np.allclose(c2w[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL):
        raise CaptureError(
            "bad_pose",
            f"{what}: the pose is not rigid (rotation off by {err:.2g}: scaled or sheared); "
            "store a rotation and a translation only",
        )


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation matrix [3, 3]."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def colmap_pose_to_c2w(q: np.ndarray, t: np.ndarray, what: str) -> np.ndarray:
    """COLMAP world-to-camera quaternion (w, x, y, z) and translation -> camera-to-world [4, 4]."""
    q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise CaptureError("bad_pose", f"{what}: the pose holds NaN or Inf; fix or drop the frame")
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > RIGID_TOL:
        raise CaptureError(
            "bad_pose", f"{what}: the quaternion has norm {norm:.4g}, not 1; store a unit quaternion"
        )
    rot = quaternion_to_rotation(q / norm)
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ t
    return c2w


def nerfstudio_to_c2w(matrix: Any, applied: np.ndarray | None, what: str) -> np.ndarray:
    """A nerfstudio ``transform_matrix`` (camera-to-world, OpenGL camera axes, 3x4 or 4x4) -> camera-to-world
    [4, 4] in OpenCV axes, in the world frame before ``applied`` (the file's ``applied_transform``, 4x4)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError("bad_pose", f"{what}: transform_matrix is not a 4x4 array of numbers") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise CaptureError("bad_pose", f"{what}: transform_matrix has shape {m.shape}, expected 4x4")
    check_rigid(m, what)
    if applied is not None:
        m = np.linalg.solve(applied, m)
    return m @ GL_TO_CV


# ----------------------------------------------------------------------------------------------- images


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) from an image file's header; ``missing_image`` / ``corrupt_image`` if unreadable."""
    if not path.is_file():
        raise CaptureError(
            "missing_image", f"{what}: image {path} does not exist; restore it or drop the frame"
        )
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - any unreadable header is a corrupt image
        raise CaptureError("corrupt_image", f"{what}: image {path} cannot be read; replace it") from None


def scaled_camera(camera: Camera, width: int, height: int, what: str) -> Camera:
    """The camera for an image of ``width`` x ``height`` read instead of its stated size: a uniform scale
    (down-scaled folders such as DL3DV's ``images_4``), else ``CaptureError("image_size_mismatch")``."""
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) * max(camera.width, camera.height) > 1.0 + 1e-6 * camera.width:  # more than a pixel apart
        raise CaptureError(
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
            raise CaptureError(
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


class CaptureImages(Sequence):
    """The frames' images as encoded bytes, read (and undistorted) on access: what the shard writer indexes.

    A pinhole frame is the file's own bytes; an undistorted frame is an uncompressed PNG of the pinhole image
    (lossless; read back at once). The undistortion map is computed once per camera."""

    def __init__(self, capture: Capture) -> None:
        self.capture = capture
        self._maps: dict[Camera, tuple[float, torch.Tensor]] = {}

    def __len__(self) -> int:
        return len(self.capture)

    def __getitem__(self, i: int) -> bytes:  # type: ignore[override]
        path, camera = self.capture.paths[i], self.capture.cameras[i]
        if not camera.distorted:
            return path.read_bytes()
        if camera not in self._maps:
            zoom = pinhole_camera(camera)[1]
            self._maps[camera] = zoom, undistortion_map(camera, zoom)
        zoom, uv = self._maps[camera]
        with Image.open(path) as im:
            out = undistort(im, camera, zoom, uv)
        buf = io.BytesIO()
        out.save(buf, format="PNG", compress_level=0)
        return buf.getvalue()


def capture_cameras(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
    """(camera-to-world float64 [F, 4, 4], normalised pinhole intrinsics float64 [F, 3, 3]) of the frames as
    converted: undistorted cameras carry their zoomed focal length."""
    pinhole: dict[Camera, Camera] = {}
    ks = []
    for cam in capture.cameras:
        if cam not in pinhole:  # one zoom search per distinct camera, not per frame
            pinhole[cam] = pinhole_camera(cam)[0]
        ks.append(normalized_intrinsics(pinhole[cam]))
    return capture.c2w, np.stack(ks)


# ----------------------------------------------------------------------------------------------- nerfstudio


def _float(meta: dict, key: str, default: float | None, what: str) -> float:
    value = meta.get(key, default)
    if value is None:
        raise CaptureError(
            "bad_intrinsics", f"{what}: no `{key}`; transforms.json must give it (top level or per frame)"
        )
    try:
        return float(value)
    except (TypeError, ValueError):
        raise CaptureError("bad_intrinsics", f"{what}: `{key}` is {value!r}, not a number") from None


def nerfstudio_camera(meta: dict, what: str) -> Camera:
    """A camera from nerfstudio keys (top level merged with a frame's own)."""
    model = str(meta.get("camera_model", "OPENCV"))
    if model not in ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE"):
        raise CaptureError(
            "unsupported_camera_model",
            f"{what}: camera_model {model} is not supported (PINHOLE, OPENCV, OPENCV_FISHEYE are); "
            "undistort the images to a pinhole camera first (nerfstudio or COLMAP's image_undistorter)",
        )
    w, h = _float(meta, "w", None, what), _float(meta, "h", None, what)
    fx = _float(meta, "fl_x", None, what)
    fy = _float(meta, "fl_y", fx, what)
    cx, cy = _float(meta, "cx", w / 2, what), _float(meta, "cy", h / 2, what)
    coeffs = {k: _float(meta, k, 0.0, what) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if model == "OPENCV_FISHEYE":
        distortion: tuple[float, ...] = tuple(coeffs[k] for k in ("k1", "k2", "k3", "k4"))
    elif model == "OPENCV":
        if coeffs["k4"] != 0.0:
            raise CaptureError("unsupported_camera_model", f"{what}: camera_model OPENCV with k4 (a fisheye "
                               "coefficient); use OPENCV_FISHEYE if the lens is a fisheye")  # fmt: skip
        distortion = tuple(coeffs[k] for k in ("k1", "k2", "p1", "p2", "k3"))
    else:
        distortion = ()
    return _checked_camera(Camera(model, int(round(w)), int(round(h)), fx, fy, cx, cy, distortion), what)


def _checked_camera(camera: Camera, what: str) -> Camera:
    values = (camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion)
    if not np.isfinite(values).all() or min(camera.fx, camera.fy, camera.width, camera.height) <= 0:
        raise CaptureError(
            "bad_intrinsics",
            f"{what}: intrinsics must be finite with positive focal length and size, got fx={camera.fx}, "
            f"fy={camera.fy}, {camera.width}x{camera.height}",
        )
    return camera


def find_one(scene: Path, pattern: str, what: str) -> Path:
    """The one file or folder under ``scene`` matching ``pattern`` (its top level first, then any depth)."""
    found = sorted(scene.glob(pattern)) or sorted(scene.rglob(pattern))
    if len(found) != 1:
        detail = "none" if not found else ", ".join(str(p.relative_to(scene)) for p in found[:4])
        raise CaptureError("missing_capture_file", f"{what}: expected one {pattern} under {scene}, found "
                           f"{detail}; name it with --capture-path")  # fmt: skip
    return found[0]


def read_nerfstudio(scene: str | Path, transforms: str | None = None, images: str | None = None,
                    frame_order: str = "name") -> Capture:  # fmt: skip
    """Read one scene folder holding a nerfstudio ``transforms.json`` (``transforms``: its path relative to the
    scene, default: the one ``transforms.json`` found under it).

    images: a folder (relative to the JSON file) replacing the first folder of every ``file_path`` (DL3DV's
    ``images_4``); frame_order: ``name`` sorts frames by ``file_path``, ``file`` keeps the file's order."""
    scene = Path(scene)
    path = scene / transforms if transforms else find_one(scene, "transforms.json", scene.name)
    if not path.is_file():
        raise CaptureError("missing_capture_file", f"{scene.name}: {path} does not exist; check --capture-path")
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CaptureError("corrupt_capture_file", f"{scene.name}: {path} is not valid JSON ({e})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise CaptureError("too_few_frames", f"{scene.name}: {path} lists no frames")
    applied = None
    if meta.get("applied_transform") is not None:
        applied = np.eye(4)
        try:
            applied[:3] = np.asarray(meta["applied_transform"], dtype=np.float64).reshape(3, 4)
        except (TypeError, ValueError):
            raise CaptureError("bad_pose", f"{scene.name}: applied_transform is not a 3x4 matrix") from None
        check_rigid(applied, f"{scene.name}: applied_transform")
    top = {k: v for k, v in meta.items() if k not in ("frames", "applied_transform")}
    entries = []
    for i, frame in enumerate(frames):
        what = f"{scene.name}: frame {i}"
        if not isinstance(frame, dict) or not frame.get("file_path"):
            raise CaptureError("missing_image", f"{what}: no file_path; every frame needs its image")
        what = f"{scene.name}: frame {frame['file_path']}"
        if frame.get("transform_matrix") is None:
            raise CaptureError(
                "missing_pose", f"{what}: no transform_matrix; give every frame a pose or drop it"
            )
        entries.append((str(frame["file_path"]), frame, what))
    if frame_order == "name":
        entries.sort(key=lambda e: e[0])
    elif frame_order != "file":
        raise ValueError(f"frame_order must be 'name' or 'file', got {frame_order!r}")
    names, paths, c2w, cameras = [], [], [], []
    for file_path, frame, what in entries:
        rel = Path(file_path)
        if images:
            rel = Path(images, *rel.parts[1:]) if len(rel.parts) > 1 else Path(images, rel)
        image_path = path.parent / rel
        camera = nerfstudio_camera({**top, **frame}, what)
        width, height = image_size(image_path, what)
        names.append(file_path)
        paths.append(image_path)
        c2w.append(nerfstudio_to_c2w(frame["transform_matrix"], applied, what))
        cameras.append(scaled_camera(camera, width, height, what))
    return Capture(scene.name, names, paths, np.stack(c2w), cameras)


# ----------------------------------------------------------------------------------------------- COLMAP


def _colmap_camera(model: str, width: int, height: int, params: list[float], what: str) -> Camera:
    """A camera from a COLMAP model name and its parameter list."""
    if model not in SUPPORTED_MODELS:
        raise CaptureError(
            "unsupported_camera_model",
            f"{what}: COLMAP camera model {model} is not supported ({', '.join(SUPPORTED_MODELS)} are); "
            "undistort the model with `colmap image_undistorter` and convert its output",
        )
    names = dict(COLMAP_MODELS.values())[model]
    if len(params) != len(names):
        raise CaptureError(
            "bad_intrinsics", f"{what}: {model} takes {len(names)} parameters, got {len(params)}"
        )
    p = dict(zip(names, (float(v) for v in params)))
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    if model == "SIMPLE_RADIAL":
        distortion: tuple[float, ...] = (p["k1"], 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        distortion = (p["k1"], p["k2"], 0.0, 0.0)
    elif model in ("OPENCV", "FULL_OPENCV"):
        distortion = tuple(p[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6") if k in p)
    elif model == "OPENCV_FISHEYE":
        distortion = tuple(p[k] for k in ("k1", "k2", "k3", "k4"))
    else:
        distortion = ()
    return _checked_camera(Camera(model, int(width), int(height), fx, fy, p["cx"], p["cy"], distortion), what)


def _read_text_lines(path: Path) -> list[str]:
    return [line.rstrip("\n") for line in path.read_text().splitlines() if not line.startswith("#")]


def read_colmap_cameras(path: str | Path) -> dict[int, tuple[str, int, int, list[float]]]:
    """``cameras.txt`` / ``cameras.bin`` -> {camera id: (model name, width, height, params)}."""
    path = Path(path)
    out = {}
    if path.suffix == ".txt":
        for line in _read_text_lines(path):
            if line.strip():
                cid, model, w, h, *params = line.split()
                out[int(cid)] = (model, int(w), int(h), [float(v) for v in params])
        return out
    data = path.read_bytes()
    (count,), pos = struct.unpack_from("<Q", data, 0), 8
    for _ in range(count):
        cid, model_id, w, h = struct.unpack_from("<iiQQ", data, pos)
        pos += 24
        if model_id not in COLMAP_MODELS:
            raise CaptureError("unsupported_camera_model", f"{path}: unknown COLMAP camera model id {model_id}")
        name, params = COLMAP_MODELS[model_id]
        out[cid] = (name, w, h, list(struct.unpack_from(f"<{len(params)}d", data, pos)))
        pos += 8 * len(params)
    return out


def read_colmap_images(path: str | Path) -> dict[int, tuple[np.ndarray, np.ndarray, int, str]]:
    """``images.txt`` / ``images.bin`` -> {image id: (quaternion wxyz [4], translation [3], camera id, name)},
    world-to-camera. The 2D points are skipped."""
    path = Path(path)
    out = {}
    if path.suffix == ".txt":
        lines = _read_text_lines(path)
        for header in lines[0::2]:  # each image: a header line, then its (possibly empty) points line
            if not header.strip():
                continue
            fields = header.split(maxsplit=9)
            values = [float(v) for v in fields[1:8]]
            out[int(fields[0])] = (np.array(values[:4]), np.array(values[4:7]), int(fields[8]), fields[9])
        return out
    data = path.read_bytes()
    (count,), pos = struct.unpack_from("<Q", data, 0), 8
    for _ in range(count):
        iid, *pose = struct.unpack_from("<i7d", data, pos)
        (cid,) = struct.unpack_from("<i", data, pos + 60)
        end = data.index(b"\0", pos + 64)
        name = data[pos + 64 : end].decode("utf-8")
        (points,) = struct.unpack_from("<Q", data, end + 1)
        pos = end + 9 + points * 24  # x, y (doubles) and a point3D id (int64) per 2D point
        out[iid] = (np.array(pose[:4]), np.array(pose[4:]), cid, name)
    return out


def read_colmap(scene: str | Path, model: str | None = None, images: str | None = None) -> Capture:
    """Read one scene folder holding a COLMAP sparse model (``model``: its folder relative to the scene,
    default: the one folder under it holding ``cameras`` and ``images`` files) and its images (``images``:
    the folder, relative to the scene, the model's image names are relative to; default ``images``).
    Frames are the model's registered images sorted by name."""
    scene = Path(scene)
    if model:
        folder = scene / model
    else:
        found = sorted({p.parent for ext in ("bin", "txt") for p in scene.rglob(f"cameras.{ext}")})
        if len(found) != 1:
            detail = "none" if not found else ", ".join(str(p.relative_to(scene)) for p in found[:4])
            raise CaptureError(
                "missing_capture_file",
                f"{scene.name}: expected one COLMAP model (cameras.bin or .txt) under {scene}, found {detail}; "
                "name it with --capture-path",
            )
        folder = found[0]
    files = {}
    for kind in ("cameras", "images"):
        candidates = [folder / f"{kind}.bin", folder / f"{kind}.txt"]
        files[kind] = next((p for p in candidates if p.is_file()), None)
        if files[kind] is None:
            raise CaptureError(
                "missing_capture_file", f"{scene.name}: {folder} has no {kind}.bin or {kind}.txt"
            )
    try:
        cams = read_colmap_cameras(files["cameras"])
        imgs = read_colmap_images(files["images"])
    except CaptureError:
        raise
    except Exception as e:  # noqa: BLE001 - a truncated or garbled model file: one line, then the next scene
        raise CaptureError("corrupt_capture_file", f"{scene.name}: cannot parse the COLMAP model in {folder} "
                           f"({type(e).__name__}: {e})") from None  # fmt: skip
    if not imgs:
        raise CaptureError("too_few_frames", f"{scene.name}: the COLMAP model registers no image")
    root = scene / (images or "images")
    names, paths, c2w, cameras = [], [], [], []
    for q, t, cid, name in sorted(imgs.values(), key=lambda e: e[3]):
        what = f"{scene.name}: frame {name}"
        if cid not in cams:
            raise CaptureError("bad_intrinsics", f"{what}: camera {cid} is not in {files['cameras'].name}")
        camera = _colmap_camera(*cams[cid], what)
        width, height = image_size(root / name, what)
        names.append(name)
        paths.append(root / name)
        c2w.append(colmap_pose_to_c2w(q, t, what))
        cameras.append(scaled_camera(camera, width, height, what))
    return Capture(scene.name, names, paths, np.stack(c2w), cameras)


def read_capture(fmt: str, scene: str | Path, capture_path: str | None = None, images: str | None = None,
                 frame_order: str = "name") -> Capture:  # fmt: skip
    """Read a scene folder in ``fmt`` (``nerfstudio`` or ``colmap``); see :func:`read_nerfstudio`,
    :func:`read_colmap`. COLMAP frames are always in name order."""
    if fmt == "nerfstudio":
        return read_nerfstudio(scene, capture_path, images, frame_order)
    if fmt == "colmap":
        return read_colmap(scene, capture_path, images)
    raise ValueError(f"unknown capture format {fmt!r}; choose from {FORMATS}")
