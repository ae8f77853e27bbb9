"""A prediction's cameras as a nerfstudio ``transforms.json``, with its images and a point cloud to start from.

Layout (what nerfstudio's ``nerfstudio-data`` parser, ``ns-train splatfacto`` included, reads)::

    DEST/images/NN_NAME.png     the input images as the model saw them
    DEST/transforms.json        per frame: file_path, transform_matrix, fl_x, fl_y, cx, cy, w, h
    DEST/sparse_pc.ply          the Gaussian centres with their base colours (``ply_file_path``)

``file_path`` names each image by its file name in ``inputs/`` as it is (JSON carries any name; a byte that is
not UTF-8 is written as Python's ``\\udcXX`` escape, which Python reads back to the same file).
``transform_matrix`` is camera-to-world with OpenGL / Blender camera axes (x right, y up, z backward): this
project's OpenCV camera-to-world with its y and z columns negated. Intrinsics are in pixels, pixel centres at
(u + 0.5, v + 0.5) as here. The camera model is ``OPENCV`` with zero distortion, what ``ns-process-data``
writes for an undistorted capture.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry import denormalize_intrinsics
from .prediction import PredictedScene

CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse


def transforms_json(scene: PredictedScene, names: list[str]) -> dict:
    """The ``transforms.json`` content for ``scene`` with images ``images/NAME``."""
    w, h = scene.width, scene.height
    frames = []
    pixels = denormalize_intrinsics(scene.intrinsics.double(), h, w).numpy()
    for i, name in enumerate(names):
        c2w = scene.extrinsics[i].double().numpy() @ CV_TO_GL
        k = pixels[i]
        frames.append({
            "file_path": f"images/{name}",
            "transform_matrix": c2w.tolist(),
            "fl_x": k[0, 0], "fl_y": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "w": w, "h": h,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        })  # fmt: skip
    return {"camera_model": "OPENCV", "ply_file_path": "sparse_pc.ply", "frames": frames}


def write_point_cloud(path: Path, scene: PredictedScene) -> None:
    """The Gaussian centres and base colours as a binary PLY point cloud (x y z float, red green blue uchar)."""
    g = scene.gaussians
    n = g.num_gaussians
    table = np.zeros(n, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    table["xyz"] = g.means[0].float().numpy()
    table["rgb"] = scene.base_colors()
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}", "property float x",
              "property float y", "property float z", "property uchar red", "property uchar green",
              "property uchar blue", "end_header"]  # fmt: skip
    path.write_bytes(("\n".join(header) + "\n").encode("ascii") + table.tobytes())


def write_nerfstudio(scene: PredictedScene, dest: str | Path) -> Path:
    """Write ``transforms.json``, the images and the point cloud of ``scene`` into ``dest`` (returned)."""
    dest = Path(dest)
    names = scene.copy_images(dest / "images")
    write_point_cloud(dest / "sparse_pc.ply", scene)
    text = json.dumps(transforms_json(scene, names), indent=2, allow_nan=False)  # strict JSON, never a bare NaN
    (dest / "transforms.json").write_text(text + "\n")
    return dest
