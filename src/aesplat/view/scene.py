"""What ``aesplat view`` shows: the Gaussians, the input cameras with their images, and the novel-view path.

Three sources: a prediction folder of ``aesplat predict`` (its PLY, cameras and input images), a 3DGS PLY
alone (no cameras), or a checkpoint and images (predicted here, nothing written). The Gaussians of a folder or
a PLY carry the SH bands the PLY holds (``aesplat predict`` writes up to degree 3 unless ``--ply-sh-degree``);
a prediction made here carries all of the model's.

What is loaded is checked before the server starts, so that no browser session meets it: a PLY or a folder with
no Gaussians to show is one line; Gaussians holding NaN or Inf are dropped with one line saying how many
(``read_ply``); a prediction folder's names and links are checked as ``aesplat export`` checks them
(``read_prediction``). Camera names are sent to the browser as UTF-8 (:func:`shown_name`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..errors import MissingFileError, UserError
from ..export import read_ply, read_prediction
from ..types import Gaussians


@dataclass(frozen=True)
class ViewCamera:
    """One input camera: its name, image (uint8 [H, W, 3]), camera-to-world [4, 4] and normalised
    intrinsics [3, 3] (float32), and the image size."""

    name: str
    image: np.ndarray
    extrinsics: Tensor
    intrinsics: Tensor
    width: int
    height: int


@dataclass(frozen=True)
class ViewScene:
    """Everything the viewer shows of one scene.

    gaussians         Gaussians [1, N, ...]
    cameras           the input views (none for a PLY alone)
    path_extrinsics   [F, 4, 4] the novel-view path (camera-to-world; F = 0 without one)
    path_intrinsics   [F, 3, 3] normalised
    background        [3] the colour renders are composited over
    render_options    ``RenderSettings`` fields the renders use (as ``aesplat predict`` rendered)
    source            what was opened, for the page title
    """

    gaussians: Gaussians
    cameras: list[ViewCamera]
    path_extrinsics: Tensor
    path_intrinsics: Tensor
    background: Tensor
    render_options: dict = field(default_factory=dict)
    source: str = ""

    @property
    def sh_degree(self) -> int:
        return self.gaussians.sh_degree


def shown_name(name: str) -> str:
    """``name`` as text the browser can be sent (UTF-8): a byte of a file name that is not UTF-8, which Python
    holds as a lone surrogate, is shown as its escape (``\\xff``); any other name is kept as it is."""
    try:
        raw = name.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a lone surrogate that stands for no byte (written into cameras.json by hand)
        return name.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")


def _showable(gaussians: Gaussians, ply: Path) -> Gaussians:
    """``gaussians`` if there is one to show; else a UserError naming the PLY ``ply``."""
    if gaussians.num_gaussians == 0:
        raise UserError(f"{str(ply)!r} holds no Gaussians to show (none, or none with finite values); give a "
                        "PLY that holds some")  # fmt: skip
    return gaussians


def _read_rgb(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"))


def scene_from_path(path: str | Path) -> ViewScene:
    """A prediction folder or a 3DGS ``.ply`` file; anything else, or one without a Gaussian to show, is one
    UserError."""
    path = Path(path)
    if path.is_dir():
        pred = read_prediction(path)
        gaussians = _showable(pred.gaussians, path / "gaussians.ply")
        size = pred.width, pred.height
        cameras = [
            ViewCamera(shown_name(name), _read_rgb(img), pred.extrinsics[i], pred.intrinsics[i], *size)
            for i, (name, img) in enumerate(zip(pred.names, pred.images))
        ]
        return ViewScene(gaussians, cameras, pred.novel_extrinsics, pred.novel_intrinsics, pred.background,
                         pred.render_options, source=str(path))  # fmt: skip
    if not path.exists():
        raise MissingFileError(f"{str(path)!r} does not exist; give a prediction folder or a 3DGS .ply file")
    if path.suffix.lower() != ".ply":
        raise UserError(f"{str(path)!r} is neither a prediction folder nor a .ply file")
    no_path = torch.zeros(0, 4, 4), torch.zeros(0, 3, 3)
    return ViewScene(_showable(read_ply(path), path), [], *no_path, torch.zeros(3), source=str(path))


def scene_from_checkpoint(
    ckpt: str | Path,
    images: list[str],
    *,
    size: int | None = None,
    crop: str = "none",
    device: str = "cpu",
    path_frames: int = 30,
    intrinsics: tuple[float, float, float, float] | None = None,
) -> ViewScene:
    """Predict a scene from ``images`` with the checkpoint ``ckpt`` as ``aesplat predict`` does (the first
    photo's shape for every view, ``size`` its shorter side, ``crop`` as ``--crop``), in memory: nothing is
    written."""
    from ..camera_path import interpolate_cameras
    from ..commands import resolve_device
    from ..images import to_uint8
    from ..inference import predict_photos

    if len(images) < 2:
        raise UserError("give at least two images of the same scene after --ckpt")
    photos = predict_photos(ckpt, images, size=size, crop=crop, device=resolve_device(device),
                            intrinsics=intrinsics)  # fmt: skip
    loaded, pixels, pred, shape = photos.loaded, photos.images, photos.pred, photos.shape
    background = loaded.background
    ext, intr = pred.extrinsics.cpu(), pred.intrinsics.cpu()
    height, width = shape
    cameras = [
        ViewCamera(shown_name(Path(p).stem), to_uint8(pixels[i]), ext[i], intr[i], width, height)
        for i, p in enumerate(images)
    ]
    path_ext, path_int = interpolate_cameras(ext, intr, path_frames)
    options = dict(loaded.render.get("options", {}))
    return ViewScene(pred.gaussians.to("cpu"), cameras, path_ext, path_int, background, options,
                     source=f"{Path(ckpt).name} on {len(images)} images")  # fmt: skip
