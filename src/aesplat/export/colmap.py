"""A prediction's cameras as a COLMAP text model, with its images and the Gaussian centres as 3D points.

Layout (what COLMAP, nerfstudio's ``colmap`` data parser and gsplat's example trainer read)::

    DEST/images/NN_NAME.png        the input images as the model saw them
    DEST/image_names.json          each image's file name -> the view's name (its photo's, in cameras.json)
    DEST/sparse/0/cameras.txt      one PINHOLE camera per image: width, height, fx, fy, cx, cy in pixels
    DEST/sparse/0/images.txt       world-to-camera rotation (quaternion w, x, y, z) and translation per image
    DEST/sparse/0/points3D.txt     one point per Gaussian: centre and base colour, no tracks

COLMAP (and pycolmap, which gsplat's trainer reads with) takes an image's NAME up to the next space,
nerfstudio's reader splits the line on any whitespace, and every reader ends it at a line break: a photo name
with whitespace, a line break or another character that is not printable (a byte that is not UTF-8 included)
is written with each such character replaced by ``_`` (:func:`colmap_file_name`). The view number in front
keeps every name distinct, and ``image_names.json`` records which photo each file is.

COLMAP uses OpenCV camera axes and puts pixel centres at (u + 0.5, v + 0.5), as this project does, so the
pixel principal point is the normalised one times the image size. Numbers are written with 17 significant
digits: the model reads back exactly what was predicted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry import denormalize_intrinsics, invert_pose, matrix_to_quat
from .prediction import PredictedScene


def _num(x: float) -> str:
    return f"{float(x):.17g}"


def colmap_file_name(index: int, name: str) -> str:
    """The file name of view ``index``'s image (``name``: its photo's) in a COLMAP export, ``NN_NAME.png``, with
    each character a COLMAP text model cannot carry in a name (whitespace, line breaks, other characters that
    are not printable, bytes that are not UTF-8) replaced by ``_``; any other name is kept as it is."""
    safe = "".join(c if c.isprintable() and not c.isspace() else "_" for c in name)
    return f"{index:02d}_{safe}.png"


def colmap_camera_lines(scene: PredictedScene) -> list[str]:
    """``cameras.txt`` data lines: camera i + 1 is image i's PINHOLE camera."""
    w, h = scene.width, scene.height
    lines = []
    for i, k in enumerate(denormalize_intrinsics(scene.intrinsics.double(), h, w)):
        params = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        lines.append(f"{i + 1} PINHOLE {w} {h} " + " ".join(_num(p) for p in params))
    return lines


def colmap_image_lines(scene: PredictedScene, names: list[str]) -> list[str]:
    """``images.txt`` lines: for image i + 1 its pose line, then an empty line (no 2D points)."""
    w2c = invert_pose(scene.extrinsics.double())  # [V, 4, 4]
    quats = matrix_to_quat(w2c[:, :3, :3])  # [V, 4] (w, x, y, z)
    lines = []
    for i, name in enumerate(names):
        values = [*quats[i].tolist(), *w2c[i, :3, 3].tolist()]
        lines += [f"{i + 1} " + " ".join(_num(v) for v in values) + f" {i + 1} {name}", ""]
    return lines


def colmap_point_lines(scene: PredictedScene) -> list[str]:
    """``points3D.txt`` data lines: every Gaussian's centre and base colour (0..255), error 0, no track."""
    g = scene.gaussians
    means = g.means[0].double().numpy()  # [N, 3]
    rgb = scene.base_colors()  # [N, 3]
    return [
        f"{i + 1} {_num(x)} {_num(y)} {_num(z)} {r} {gr} {b} 0"
        for i, ((x, y, z), (r, gr, b)) in enumerate(zip(means, rgb.astype(np.int64)))
    ]


def write_colmap(scene: PredictedScene, dest: str | Path) -> Path:
    """Write the COLMAP text model and images of ``scene`` into the folder ``dest``; returns ``dest``."""
    dest = Path(dest)
    names = scene.copy_images(dest / "images", [colmap_file_name(i, n) for i, n in enumerate(scene.names)])
    (dest / "image_names.json").write_text(json.dumps(dict(zip(names, scene.names)), indent=2) + "\n")
    model = dest / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    v, n = scene.num_views, scene.gaussians.num_gaussians
    files = {
        "cameras.txt": [
            "# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {v}",
            *colmap_camera_lines(scene),
        ],
        "images.txt": [
            "# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {v}, mean observations per image: 0",
            *colmap_image_lines(scene, names),
        ],
        "points3D.txt": [
            "# 3D point list with one line of data per point:",
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
            f"# Number of points: {n}, mean track length: 0",
            *colmap_point_lines(scene),
        ],
    }
    for name, lines in files.items():
        (model / name).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return dest
