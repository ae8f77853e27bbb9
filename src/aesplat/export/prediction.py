"""A folder written by ``aesplat predict``, read back: the cameras, the input images and the Gaussians.

What is read (see ``aesplat.predict``): ``cameras.json`` (every input view's camera-to-world and normalised
intrinsics, the novel-view path, and the background and renderer options the renders used), ``inputs/`` (the
images as the model saw them) and ``gaussians.ply``. The exporters and ``aesplat view`` start from here.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..errors import MissingFileError, UserError
from ..geometry import sh_dc_to_rgb
from ..types import Gaussians
from .ply import read_ply


@dataclass(frozen=True)
class PredictedScene:
    """One scene as ``aesplat predict`` wrote it.

    names             image names (the input files' stems), one per view, in input order
    images            paths of the input images as the model saw them (``inputs/NN_NAME.png``)
    extrinsics        [V, 4, 4] camera-to-world, OpenCV axes, world = view 0's camera frame
    intrinsics        [V, 3, 3] normalised (fx, cx / width; fy, cy / height)
    width, height     the input images' size in pixels
    novel_extrinsics  [F, 4, 4] the novel-view path (camera-to-world)
    novel_intrinsics  [F, 3, 3] normalised
    gaussians         Gaussians [1, N, ...] of ``gaussians.ply``
    background        [3] the colour the renders were composited over
    render_options    the ``RenderSettings`` fields the renders used (keyword arguments of ``render``)
    """

    root: Path
    names: list[str]
    images: list[Path]
    extrinsics: Tensor
    intrinsics: Tensor
    width: int
    height: int
    novel_extrinsics: Tensor
    novel_intrinsics: Tensor
    gaussians: Gaussians
    background: Tensor
    render_options: dict = field(default_factory=dict)

    @property
    def num_views(self) -> int:
        return len(self.names)

    def copy_images(self, folder: Path) -> list[str]:
        """Copy the input images into ``folder`` (created); returns their file names, in view order."""
        folder.mkdir(parents=True, exist_ok=True)
        for src in self.images:
            shutil.copyfile(src, folder / src.name)
        return [src.name for src in self.images]

    def base_colors(self) -> np.ndarray:
        """Every Gaussian's base colour (SH degree 0), uint8 [N, 3]: what point clouds and ``.splat`` store."""
        rgb = sh_dc_to_rgb(self.gaussians.sh[0, :, 0]).clamp(0, 1)
        return (rgb * 255).round().to(torch.uint8).numpy()


def _matrices(records: list[dict], key: str) -> Tensor:
    return torch.tensor([r[key] for r in records], dtype=torch.float32)


def read_prediction(folder: str | Path) -> PredictedScene:
    """Read the output folder of ``aesplat predict``; a folder that holds no prediction is one UserError."""
    root = Path(folder)
    if not root.is_dir():
        raise MissingFileError(f"{str(root)!r} is not a folder; give the --out folder of `aesplat predict`")
    missing = [name for name in ("cameras.json", "gaussians.ply", "inputs") if not (root / name).exists()]
    if missing:
        raise UserError(
            f"{str(root)!r} holds no prediction (no {', '.join(missing)}); give the --out folder of "
            "`aesplat predict`"
        )
    try:
        cameras = json.loads((root / "cameras.json").read_text())
        views = cameras["views"]
        width, height = int(views[0]["width"]), int(views[0]["height"])
        extrinsics = _matrices(views, "camera_to_world")
        intrinsics = _matrices(views, "intrinsics_normalized")
        novel = cameras.get("novel") or []
        names = [str(v["image"]) for v in views]
    except (ValueError, KeyError, IndexError, TypeError) as err:
        raise UserError(
            f"{str(root / 'cameras.json')!r} is not the cameras file of `aesplat predict` "
            f"({type(err).__name__}: {err})"
        ) from None
    images = [root / "inputs" / f"{i:02d}_{name}.png" for i, name in enumerate(names)]
    if absent := [p for p in images if not p.is_file()]:
        raise UserError(f"{str(root)!r}: input image {absent[0].name} named in cameras.json is missing")
    render_record = cameras.get("render") or {}
    return PredictedScene(
        root=root,
        names=names,
        images=images,
        extrinsics=extrinsics,
        intrinsics=intrinsics,
        width=width,
        height=height,
        novel_extrinsics=_matrices(novel, "camera_to_world") if novel else torch.zeros(0, 4, 4),
        novel_intrinsics=_matrices(novel, "intrinsics_normalized") if novel else torch.zeros(0, 3, 3),
        gaussians=read_ply(root / "gaussians.ply"),
        background=torch.tensor(render_record.get("background", (0.0, 0.0, 0.0)), dtype=torch.float32),
        render_options=dict(render_record.get("options") or {}),
    )
