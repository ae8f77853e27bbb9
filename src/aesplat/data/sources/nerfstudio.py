"""nerfstudio captures (DL3DV, ScanNet++): a scene folder holding a ``transforms.json`` and its images.

``transform_matrix`` is camera-to-world with OpenGL / Blender camera axes (x right, y up, z backward), so its y
and z columns are negated. An ``applied_transform`` (the 3x4 world transform ``ns-process-data`` applied to the
original poses) is undone, so the world frame is the capture's own. Intrinsics (``fl_x``, ``fl_y``, ``cx``,
``cy``, ``w``, ``h``, distortion) sit at the top level or per frame (a frame's value wins). ``file_path`` is
relative to the JSON file and must stay inside the scene folder.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..lens import Camera, checked_camera, scaled_camera
from ..scene import Scene, SceneError
from ..validate import check_rigid, inside_folder
from .folders import FolderReader, capture_scene, find_one, image_size

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z: OpenGL / Blender axes <-> OpenCV axes
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE")


def nerfstudio_to_c2w(matrix: Any, applied: np.ndarray | None, what: str) -> np.ndarray:
    """A nerfstudio ``transform_matrix`` (camera-to-world, OpenGL camera axes, 3x4 or 4x4) -> camera-to-world
    [4, 4] in OpenCV axes, in the world frame before ``applied`` (the file's ``applied_transform``, 4x4)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError("bad_pose", f"{what}: transform_matrix is not a 4x4 array of numbers") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise SceneError("bad_pose", f"{what}: transform_matrix has shape {m.shape}, expected 4x4")
    check_rigid(m, what)
    if applied is not None:
        m = np.linalg.solve(applied, m)
    return m @ GL_TO_CV


def _float(meta: dict, key: str, default: float | None, what: str) -> float:
    value = meta.get(key, default)
    if value is None:
        raise SceneError(
            "bad_intrinsics", f"{what}: no `{key}`; transforms.json must give it (top level or per frame)"
        )
    try:
        return float(value)
    except (TypeError, ValueError):
        raise SceneError("bad_intrinsics", f"{what}: `{key}` is {value!r}, not a number") from None


def nerfstudio_camera(meta: dict, what: str) -> Camera:
    """A camera from nerfstudio keys (top level merged with a frame's own)."""
    model = str(meta.get("camera_model", "OPENCV"))
    if model not in CAMERA_MODELS:
        raise SceneError(
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
            raise SceneError("unsupported_camera_model", f"{what}: camera_model OPENCV with k4 (a fisheye "
                             "coefficient); use OPENCV_FISHEYE if the lens is a fisheye")  # fmt: skip
        distortion = tuple(coeffs[k] for k in ("k1", "k2", "p1", "p2", "k3"))
    else:
        distortion = ()
    return checked_camera(Camera(model, int(round(w)), int(round(h)), fx, fy, cx, cy, distortion), what)


def read_nerfstudio(scene: Path, transforms: str | None = None, images: str | None = None,
                    frame_order: str = "name", dataset: str = "") -> Scene:  # fmt: skip
    """Read one scene folder holding a nerfstudio ``transforms.json`` (``transforms``: its path relative to the
    scene, default: the one ``transforms.json`` found under it).

    images: a folder (relative to the JSON file) replacing the first folder of every ``file_path`` (DL3DV's
    ``images_4``); frame_order: ``name`` sorts frames by ``file_path``, ``file`` keeps the file's order."""
    if transforms:
        path = inside_folder(scene, transforms, f"{scene.name}: --capture-path")
    else:
        path = find_one(scene, "transforms.json", scene.name)
    if not path.is_file():
        raise SceneError("missing_capture_file", f"{scene.name}: {path} does not exist; check --capture-path")
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SceneError("corrupt_capture_file", f"{scene.name}: {path} is not valid JSON ({e})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise SceneError("too_few_frames", f"{scene.name}: {path} lists no frames")
    applied = None
    if meta.get("applied_transform") is not None:
        applied = np.eye(4)
        try:
            applied[:3] = np.asarray(meta["applied_transform"], dtype=np.float64).reshape(3, 4)
        except (TypeError, ValueError):
            raise SceneError("bad_pose", f"{scene.name}: applied_transform is not a 3x4 matrix") from None
        check_rigid(applied, f"{scene.name}: applied_transform")
    top = {k: v for k, v in meta.items() if k not in ("frames", "applied_transform")}
    entries = []
    for i, frame in enumerate(frames):
        what = f"{scene.name}: frame {i}"
        if not isinstance(frame, dict) or not frame.get("file_path"):
            raise SceneError("missing_image", f"{what}: no file_path; every frame needs its image")
        what = f"{scene.name}: frame {frame['file_path']}"
        if frame.get("transform_matrix") is None:
            raise SceneError("missing_pose", f"{what}: no transform_matrix; give every frame a pose or drop it")
        entries.append((str(frame["file_path"]), frame, what))
    if frame_order == "name":
        entries.sort(key=lambda e: e[0])
    names, paths, c2w, cameras = [], [], [], []
    for file_path, frame, what in entries:
        rel = Path(file_path)
        if images and not rel.is_absolute():
            rel = Path(images, *rel.parts[1:]) if len(rel.parts) > 1 else Path(images, rel)
        image_path = inside_folder(scene, rel, what, start=path.parent)
        camera = nerfstudio_camera({**top, **frame}, what)
        width, height = image_size(image_path, what)
        names.append(file_path)
        paths.append(image_path)
        c2w.append(nerfstudio_to_c2w(frame["transform_matrix"], applied, what))
        cameras.append(scaled_camera(camera, width, height, what))
    return capture_scene(scene.name, dataset, names, paths, c2w, cameras, [path])


class NerfstudioReader(FolderReader):
    """Scene folders each holding a nerfstudio ``transforms.json`` (``--capture-path`` names it)."""

    def read(self, folder: Path) -> Scene:
        cfg = self.cfg
        return read_nerfstudio(folder, cfg.capture_path, cfg.images, cfg.frame_order, self.dataset())
