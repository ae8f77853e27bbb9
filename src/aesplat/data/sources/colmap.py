"""COLMAP sparse models (your own capture): a scene folder holding ``cameras`` and ``images`` (``.txt`` or
``.bin``, the layout documented at https://colmap.github.io/format.html) and the image files.

Each image holds a world-to-camera rotation (unit quaternion w, x, y, z) and translation in OpenCV axes;
cameras hold pixel intrinsics and the lens. ``points3D`` is not needed. Image names are relative to the image
folder and must stay inside the scene folder. Frames are the registered images sorted by name.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..lens import SUPPORTED_MODELS, Camera, checked_camera, scaled_camera
from ..scene import Scene, SceneError
from ..validate import RIGID_TOL, inside_folder
from .folders import FolderReader, capture_scene, image_size

# COLMAP camera models: id -> (name, parameter names).
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

ColmapCameras = dict[int, tuple[str, int, int, list[float]]]  # id -> (model, width, height, params)
ColmapImages = dict[int, tuple[np.ndarray, np.ndarray, int, str]]  # id -> (qvec wxyz, tvec, camera id, name)


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
        raise SceneError("bad_pose", f"{what}: the pose holds NaN or Inf; fix or drop the frame")
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > RIGID_TOL:
        raise SceneError(
            "bad_pose", f"{what}: the quaternion has norm {norm:.4g}, not 1; store a unit quaternion"
        )
    rot = quaternion_to_rotation(q / norm)
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ t
    return c2w


def colmap_camera(model: str, width: int, height: int, params: list[float], what: str) -> Camera:
    """A camera from a COLMAP model name and its parameter list."""
    if model not in SUPPORTED_MODELS:
        raise SceneError(
            "unsupported_camera_model",
            f"{what}: COLMAP camera model {model} is not supported ({', '.join(SUPPORTED_MODELS)} are); "
            "undistort the model with `colmap image_undistorter` and convert its output",
        )
    names = dict(COLMAP_MODELS.values())[model]
    if len(params) != len(names):
        raise SceneError("bad_intrinsics", f"{what}: {model} takes {len(names)} parameters, got {len(params)}")
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
    return checked_camera(Camera(model, int(width), int(height), fx, fy, p["cx"], p["cy"], distortion), what)


def _text_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of every line that is not a comment; blank lines kept (they mean something)."""
    return [(n, line.strip()) for n, line in enumerate(path.read_text().splitlines(), 1)
            if not line.lstrip().startswith("#")]  # fmt: skip


def read_colmap_cameras(path: Path) -> ColmapCameras:
    """``cameras.txt`` / ``cameras.bin`` -> {camera id: (model name, width, height, params)}."""
    out: ColmapCameras = {}
    if path.suffix == ".txt":
        for _, line in _text_lines(path):
            if line:
                cid, model, w, h, *params = line.split()
                out[int(cid)] = (model, int(w), int(h), [float(v) for v in params])
        return out
    data = path.read_bytes()
    (count,), pos = struct.unpack_from("<Q", data, 0), 8
    for _ in range(count):
        cid, model_id, w, h = struct.unpack_from("<iiQQ", data, pos)
        pos += 24
        if model_id not in COLMAP_MODELS:
            raise SceneError("unsupported_camera_model", f"{path}: unknown COLMAP camera model id {model_id}")
        name, params = COLMAP_MODELS[model_id]
        out[cid] = (name, w, h, list(struct.unpack_from(f"<{len(params)}d", data, pos)))
        pos += 8 * len(params)
    return out


def _number(token: str) -> float | None:
    try:
        return float(token)
    except ValueError:
        return None


def _image_header(line: str) -> tuple[int, np.ndarray, np.ndarray, int, str] | None:
    """An ``images.txt`` header line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME) parsed, or None if the
    line is not one (a POINTS2D line: numbers only)."""
    fields = line.split(maxsplit=9)
    if len(fields) < 10 or _number(fields[9]) is not None:  # an image name is never a bare number
        return None
    values = [_number(v) for v in fields[1:8]]
    if not fields[0].lstrip("-").isdigit() or not fields[8].lstrip("-").isdigit() or None in values:
        return None
    return int(fields[0]), np.array(values[:4]), np.array(values[4:7]), int(fields[8]), fields[9]


def read_colmap_images(path: Path) -> ColmapImages:
    """``images.txt`` / ``images.bin`` -> {image id: (quaternion wxyz [4], translation [3], camera id, name)},
    world-to-camera. The 2D points are skipped.

    The text format gives each image a header line and a POINTS2D line that may be empty. Lines are told apart
    by what they hold, not by position: a model written without POINTS2D lines, or with a stray blank line,
    reads every image."""
    out: ColmapImages = {}
    if path.suffix == ".txt":
        points_may_follow = False
        for number, line in _text_lines(path):
            header = _image_header(line) if line else None
            if header is None:
                if line and not points_may_follow and not all(_number(t) is not None for t in line.split()):
                    raise ValueError(f"line {number} is neither an image header nor a POINTS2D line")
                points_may_follow = False  # the image's POINTS2D line (possibly empty), or a stray blank
                continue
            iid, q, t, cid, name = header
            if iid in out:
                raise ValueError(f"image id {iid} appears twice (line {number})")
            out[iid] = (q, t, cid, name)
            points_may_follow = True
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


def find_model(scene: Path, model: str | None) -> tuple[Path, Path]:
    """The model's cameras and images files (``model``: its folder relative to the scene; default: the one
    folder under the scene holding a ``cameras.bin`` or ``cameras.txt``)."""
    if model:
        folder = inside_folder(scene, model, f"{scene.name}: --capture-path")
    else:
        found = sorted({p.parent for ext in ("bin", "txt") for p in scene.rglob(f"cameras.{ext}")})
        if len(found) != 1:
            detail = "none" if not found else ", ".join(str(p.relative_to(scene)) for p in found[:4])
            raise SceneError("missing_capture_file", f"{scene.name}: expected one COLMAP model (cameras.bin or "
                             f".txt) under {scene}, found {detail}; name it with --capture-path")  # fmt: skip
        folder = found[0]
    files = []
    for kind in ("cameras", "images"):
        path = next((p for p in (folder / f"{kind}.bin", folder / f"{kind}.txt") if p.is_file()), None)
        if path is None:
            raise SceneError("missing_capture_file", f"{scene.name}: {folder} has no {kind}.bin or {kind}.txt")
        files.append(path)
    return files[0], files[1]


def read_colmap(scene: Path, model: str | None = None, images: str | None = None, dataset: str = "") -> Scene:
    """Read one scene folder holding a COLMAP sparse model and its images (``images``: the folder, relative
    to the scene, the model's image names are relative to; default ``images``)."""
    cameras_file, images_file = find_model(scene, model)
    try:
        cams = read_colmap_cameras(cameras_file)
        imgs = read_colmap_images(images_file)
    except SceneError:
        raise
    except Exception as e:  # noqa: BLE001 - a truncated or garbled model file: one line, then the next scene
        raise SceneError("corrupt_capture_file", f"{scene.name}: cannot parse the COLMAP model in "
                         f"{cameras_file.parent} ({type(e).__name__}: {e})") from None  # fmt: skip
    if not imgs:
        raise SceneError("too_few_frames", f"{scene.name}: the COLMAP model registers no image")
    root = Path(images or "images")
    names, paths, c2w, cameras = [], [], [], []
    for q, t, cid, name in sorted(imgs.values(), key=lambda e: e[3]):
        what = f"{scene.name}: frame {name}"
        if cid not in cams:
            raise SceneError("bad_intrinsics", f"{what}: camera {cid} is not in {cameras_file.name}")
        camera = colmap_camera(*cams[cid], what)
        path = inside_folder(scene, root / name, what)  # an absolute name or ../ is refused
        width, height = image_size(path, what)
        names.append(name)
        paths.append(path)
        c2w.append(colmap_pose_to_c2w(q, t, what))
        cameras.append(scaled_camera(camera, width, height, what))
    return capture_scene(scene.name, dataset, names, paths, c2w, cameras, [cameras_file, images_file])


class ColmapReader(FolderReader):
    """Scene folders each holding a COLMAP sparse model (``--capture-path`` names its folder) and images."""

    def read(self, folder: Path) -> Scene:
        return read_colmap(folder, self.cfg.capture_path, self.cfg.images, self.dataset())
