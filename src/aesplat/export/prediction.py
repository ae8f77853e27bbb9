"""A folder written by ``aesplat predict``, read back: the cameras, the input images and the Gaussians.

What is read (see ``aesplat.predict``): ``cameras.json`` (every input view's camera-to-world and normalised
intrinsics, the novel-view path, and the background and renderer options the renders used), ``inputs/`` (the
images as the model saw them) and ``gaussians.ply``. The exporters and ``aesplat view`` start from here.

A prediction folder may come from anywhere, so what it holds is checked here, once for every exporter and the
viewer: names and links that lead out of the folder and cameras holding NaN or Inf are refused in one line
naming the view; Gaussians holding NaN or Inf are dropped with one line saying how many.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..data.scene import SceneError
from ..data.validate import inside_folder
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

    def copy_images(self, folder: Path, file_names: list[str] | None = None) -> list[str]:
        """Copy the input images into ``folder`` (created) as ``file_names`` (default: their names in
        ``inputs/``, ``NN_NAME.png``); returns the file names, in view order."""
        names = [src.name for src in self.images] if file_names is None else file_names
        folder.mkdir(parents=True, exist_ok=True)
        for src, name in zip(self.images, names, strict=True):
            shutil.copyfile(src, folder / name)
        return names

    def base_colors(self) -> np.ndarray:
        """Every Gaussian's base colour (SH degree 0), uint8 [N, 3]: what point clouds and ``.splat`` store."""
        rgb = sh_dc_to_rgb(self.gaussians.sh[0, :, 0]).clamp(0, 1)
        return (rgb * 255).round().to(torch.uint8).numpy()


def _matrices(records: list[dict], key: str, shape: tuple[int, int]) -> Tensor:
    """The ``key`` matrix of every record, float32 [len(records), *shape]; a ValueError if one is not so."""
    matrices = torch.tensor([r[key] for r in records], dtype=torch.float32)
    if matrices.shape[1:] != shape:
        raise ValueError(f"{key} is not {shape[0]}x{shape[1]}")
    return matrices


def _background(value: object) -> Tensor:
    """The render background [3] of ``cameras.json``; a ValueError unless it is 3 finite numbers."""
    numbers = isinstance(value, list) and all(isinstance(v, (int, float)) for v in value)
    background = torch.tensor(value if numbers else [], dtype=torch.float32)
    if background.shape != (3,) or not torch.isfinite(background).all():
        raise ValueError(f"the render background {value!r} is not 3 finite numbers")
    return background


def _check_finite(cameras_file: Path, what: list[str], extrinsics: Tensor, intrinsics: Tensor) -> None:
    """A UserError naming the first camera (``what[i]``) whose extrinsics [V, 4, 4] or intrinsics [V, 3, 3] hold
    NaN or Inf: no exporter can write it and no renderer can look through it."""
    finite = torch.isfinite(extrinsics).flatten(1).all(1) & torch.isfinite(intrinsics).flatten(1).all(1)  # [V]
    if not finite.all():
        first = int((~finite).nonzero()[0])
        raise UserError(f"{str(cameras_file)!r}: {what[first]} has a camera holding NaN or Inf; run `aesplat "
                        "predict` again")  # fmt: skip


def _input_image(root: Path, index: int, name: str) -> Path:
    """``root/inputs/NN_NAME.png``, the input image of view ``index`` named ``name`` in ``cameras.json``.

    A prediction folder may come from elsewhere; it never makes an export copy, or the viewer show, another file
    of the user's. Refused in one line naming the view: a name that climbs out of the folder (``../``: the rule
    of the capture readers), a name that holds a folder (``aesplat predict`` names each view by its photo's file
    name; ``a/b`` would lose its view number in the exports' copies), or an image that is a link leading out of
    the folder (a link to a file inside it is followed)."""
    what = f"{str(root / 'cameras.json')!r}: view {index} {name!r}"
    file = Path("inputs", f"{index:02d}_{name}.png")
    try:
        path = inside_folder(root, file, what)
    except SceneError:
        raise UserError(f"{what} names {str(file)!r}, outside the prediction folder; a prediction folder only "
                        "names files inside itself: run `aesplat predict` again") from None  # fmt: skip
    if Path(name).name != name:
        raise UserError(f"{what} is not a file name (it holds a folder); `aesplat predict` names each view by "
                        "its photo's file name: run it again")  # fmt: skip
    if not path.resolve().is_relative_to(root.resolve()):
        raise UserError(f"{what}: {str(file)!r} links outside the prediction folder (to "
                        f"{str(path.resolve())!r}); put the image itself in inputs/")  # fmt: skip
    if not path.is_file():  # names in quotes: a name may hold a line break, the message stays one line
        raise UserError(f"{str(root)!r}: input image {path.name!r} named in cameras.json is missing")
    return path


def read_prediction(folder: str | Path) -> PredictedScene:
    """Read the output folder of ``aesplat predict``; a folder that holds no prediction, or a malformed or
    unsafe one (:func:`_input_image`, :func:`_check_finite`), is one UserError. Gaussians holding NaN or Inf
    are dropped (:func:`~aesplat.export.ply.read_ply`, one line saying how many), so no export writes them."""
    root = Path(folder)
    if not root.is_dir():
        raise MissingFileError(f"{str(root)!r} is not a folder; give the --out folder of `aesplat predict`")
    missing = [name for name in ("cameras.json", "gaussians.ply", "inputs") if not (root / name).exists()]
    if missing:
        raise UserError(
            f"{str(root)!r} holds no prediction (no {', '.join(missing)}); give the --out folder of "
            "`aesplat predict`"
        )
    cameras_file = root / "cameras.json"
    try:
        cameras = json.loads(cameras_file.read_text())
        views = cameras["views"]
        width, height = int(views[0]["width"]), int(views[0]["height"])
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        extrinsics = _matrices(views, "camera_to_world", (4, 4))
        intrinsics = _matrices(views, "intrinsics_normalized", (3, 3))
        novel = cameras.get("novel") or []
        novel_extrinsics = _matrices(novel, "camera_to_world", (4, 4)) if novel else torch.zeros(0, 4, 4)
        novel_intrinsics = _matrices(novel, "intrinsics_normalized", (3, 3)) if novel else torch.zeros(0, 3, 3)
        names = [v["image"] for v in views]
        if odd := next((name for name in names if not isinstance(name, str)), None):
            raise TypeError(f"image {odd!r} is not a name")
        render_record = cameras.get("render") or {}
        if not isinstance(render_record, dict):
            raise TypeError("render is not an object")
        background = _background(render_record.get("background", [0.0, 0.0, 0.0]))
        render_options = dict(render_record.get("options") or {})
    except (ValueError, KeyError, IndexError, TypeError, AttributeError) as err:
        raise UserError(
            f"{str(cameras_file)!r} is not the cameras file of `aesplat predict` ({type(err).__name__}: {err})"
        ) from None
    _check_finite(cameras_file, [f"view {i} {name!r}" for i, name in enumerate(names)], extrinsics, intrinsics)
    _check_finite(cameras_file, [f"novel view {f}" for f in range(len(novel))], novel_extrinsics,
                  novel_intrinsics)  # fmt: skip
    images = [_input_image(root, i, name) for i, name in enumerate(names)]
    return PredictedScene(
        root=root,
        names=names,
        images=images,
        extrinsics=extrinsics,
        intrinsics=intrinsics,
        width=width,
        height=height,
        novel_extrinsics=novel_extrinsics,
        novel_intrinsics=novel_intrinsics,
        gaussians=read_ply(root / "gaussians.ply"),
        background=background,
        render_options=render_options,
    )
