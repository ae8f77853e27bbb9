"""Prediction folders and PLY files built without a model, in the layout ``aesplat predict`` writes: for the
tests of what the exporters and the viewer do with folders, names and Gaussians they did not write themselves.

A folder holds ``cameras.json`` (the views' names, cameras and the novel path), ``inputs/NN_NAME.png`` (each
view's image a different colour, so a copy shows which view it came from) and ``gaussians.ply``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from aesplat.camera_path import camera_record
from aesplat.export import gaussians_to_ply_array, ply_property_names, write_ply
from aesplat.geometry import make_pose, quat_to_matrix
from aesplat.types import Gaussians

SIZE = 20  # the images' side in pixels


def random_gaussians(n: int = 40, degree: int = 1, seed: int = 0) -> Gaussians:
    """Gaussians [1, n] with finite parameters of every kind, SH degree ``degree``."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(torch.randn(1, n, 3, generator=g), torch.randn(1, n, 4, generator=g),
                     torch.rand(1, n, 3, generator=g) * 0.1 + 0.01, torch.rand(1, n, generator=g) * 0.9 + 0.05,
                     torch.randn(1, n, k, 3, generator=g))  # fmt: skip


def random_cameras(views: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-to-world [V, 4, 4] far from the identity and normalised intrinsics [V, 3, 3], fx != fy."""
    g = torch.Generator().manual_seed(seed)
    ext = make_pose(quat_to_matrix(torch.randn(views, 4, generator=g)), torch.randn(views, 3, generator=g))
    intr = torch.eye(3).repeat(views, 1, 1)
    intr[:, 0, 0], intr[:, 1, 1] = 0.8 + torch.rand(views, generator=g), 0.9 + torch.rand(views, generator=g)
    intr[:, 0, 2], intr[:, 1, 2] = 0.5, 0.5
    return ext, intr


def view_colour(index: int) -> tuple[int, int, int]:
    """The colour of view ``index``'s image: a different one per view."""
    return (10 + 40 * index) % 256, 200, (250 - 30 * index) % 256


def write_prediction(
    root: Path,
    names: list[str] | tuple[str, ...] = ("left", "right"),
    gaussians: Gaussians | None = None,
) -> Path:
    """A prediction folder at ``root``, a view per name, as ``aesplat predict`` writes it; returns ``root``."""
    (root / "inputs").mkdir(parents=True)
    ext, intr = random_cameras(len(names))
    for i, name in enumerate(names):
        pixels = np.empty((SIZE, SIZE, 3), np.uint8)
        pixels[:] = view_colour(i)
        Image.fromarray(pixels).save(root / "inputs" / f"{i:02d}_{name}.png")
    views = [{"image": name, **camera_record(ext[i], intr[i], SIZE, SIZE)} for i, name in enumerate(names)]
    novel = [camera_record(ext[0], intr[0], SIZE, SIZE)]
    cameras = {"views": views, "novel": novel, "render": {"background": [0.0, 0.0, 0.0], "options": {}}}
    (root / "cameras.json").write_text(json.dumps(cameras, indent=2))
    write_ply(root / "gaussians.ply", random_gaussians() if gaussians is None else gaussians)
    return root


def edit_cameras(root: Path, edit: Callable[[dict], object]) -> None:
    """Change ``root/cameras.json`` in place: ``edit`` gets its content and changes it."""
    cameras = json.loads((root / "cameras.json").read_text())
    edit(cameras)
    (root / "cameras.json").write_text(json.dumps(cameras, indent=2))


def ply_bytes(names: list[str], table: np.ndarray, count: str | None = None) -> bytes:
    """A binary 3DGS PLY of float properties ``names`` and rows ``table`` [N, P]; ``count``: the text of the
    ``element vertex`` line's count (default: N)."""
    count = str(len(table)) if count is None else count
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    return ("\n".join(header) + "\n").encode() + table.astype("<f4").tobytes()


def write_ply_with(path: Path, gaussians: Gaussians, values: dict[tuple[int, str], float]) -> Path:
    """``gaussians`` [1, N] as a 3DGS PLY whose stored property ``name`` of Gaussian ``row`` is ``value`` for
    each ``(row, name): value`` (a NaN or Inf written as it is, which ``write_ply`` may not do)."""
    names = ply_property_names(gaussians.sh_degree)
    table = gaussians_to_ply_array(gaussians)
    for (row, name), value in values.items():
        table[row, names.index(name)] = value
    path.write_bytes(ply_bytes(names, table))
    return path
