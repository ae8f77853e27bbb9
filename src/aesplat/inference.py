"""A trained model on photos: the prediction of one scene (Gaussians, cameras, depth) and renders of it.

``predict_photos`` is what ``aesplat predict`` and ``aesplat view --ckpt`` run: load the checkpoint, check that
it can take the photos, read them as the model sees them, one forward pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from .checkpoint import LoadedCheckpoint, load_checkpoint
from .errors import UserError
from .images import InputImage, load_image, model_image_shape, photo_size
from .render import render
from .types import Gaussians


@dataclass(frozen=True)
class Prediction:
    """What one forward pass gives for one scene (B = 1).

    gaussians   Gaussians [1, N, ...], N = V * H * W
    extrinsics  [V, 4, 4] camera-to-world in view 0's frame
    intrinsics  [V, 3, 3] normalised
    depth       [V, H, W] predicted z-depth
    """

    gaussians: Gaussians
    extrinsics: Tensor
    intrinsics: Tensor
    depth: Tensor


@torch.no_grad()
def predict_scene(model: torch.nn.Module, images: Tensor, intrinsics: Tensor | None = None) -> Prediction:
    """Run the model on context images [V, 3, H, W] (float in [0, 1], on the model's device); ``intrinsics``
    [V, 3, 3] normalised, for a network that reads them (NAS3R's -I)."""
    out = model(images[None], None, intrinsics=None if intrinsics is None else intrinsics[None])
    return Prediction(
        gaussians=out.gaussians.to(dtype=torch.float32),
        extrinsics=out.extrinsics[0].float(),
        intrinsics=out.intrinsics[0].float(),
        depth=out.depth[0].float(),
    )


@dataclass(frozen=True)
class PhotoPrediction:
    """A checkpoint's prediction from photos, as ``aesplat predict`` and ``aesplat view --ckpt`` make it.

    images  [V, 3, H, W] what the model saw (on the device); shape (H, W); inputs: per photo, what was used
    """

    loaded: LoadedCheckpoint
    inputs: list[InputImage]
    images: Tensor
    pred: Prediction
    shape: tuple[int, int]


def photo_intrinsics(values: tuple[float, float, float, float], image: InputImage) -> Tensor:
    """``--intrinsics`` (fx, fy, cx, cy of the whole photo, normalised by its width and height) -> the
    normalised intrinsics [3, 3] of the part of the photo the model sees (its centre crop, if any)."""
    (w, h), (left, top, right, bottom) = image.source, image.crop
    fx, fy, cx, cy = values[0] * w, values[1] * h, values[2] * w - left, values[3] * h - top  # pixels
    cw, ch = right - left, bottom - top
    return torch.tensor([[fx / cw, 0.0, cx / cw], [0.0, fy / ch, cy / ch], [0.0, 0.0, 1.0]])


def predict_photos(
    ckpt: str | Path, photos: list[str], *, size: int | None, crop: str, device: torch.device,
    intrinsics: tuple[float, float, float, float] | None = None,
) -> PhotoPrediction:  # fmt: skip
    """Load ``ckpt`` and predict from ``photos`` (the first is the reference frame; every view takes the first
    photo's shape, ``size`` its shorter side, default the trained size; ``crop`` as ``--crop``). A checkpoint
    without a camera head, a count its appearance head cannot take or a size its patch does not divide is one
    line (UserError) before any photo is read. ``intrinsics`` (``--intrinsics``): fx, fy, cx, cy of every
    photo, normalised by its width and height, for a network that reads them (NAS3R's -I), which needs them."""
    loaded = load_checkpoint(ckpt, device)
    takes = bool(getattr(loaded.model, "takes_intrinsics", False))
    if takes and intrinsics is None:
        raise UserError(
            f"{ckpt} is a NAS3R-I network, which reads the cameras' intrinsics: give --intrinsics "
            "FX,FY,CX,CY (normalised by the photo's width and height, e.g. 0.86,0.86,0.5,0.5)"
        )
    if intrinsics is not None and not takes:
        raise UserError(
            f"--intrinsics is for networks that read them (NAS3R's -I checkpoints); {ckpt} predicts "
            "them itself: leave --intrinsics out"
        )
    if loaded.cameras != "predicted":
        raise UserError(
            f"{ckpt} was trained with model.cameras={loaded.cameras}: it renders with "
            "the data set's cameras, its camera head never trained, and it predicts no cameras for "
            "images. Evaluate it with `aesplat test` or `aesplat bench`, or predict with a checkpoint trained "
            "with model.cameras=predicted."
        )
    try:
        loaded.model.check_context_views(len(photos))
    except UserError:  # the training setting it names is no option here: say what predict can do instead
        raise UserError(
            f"{ckpt} has the paper's appearance head, which takes {loaded.model.cfg.num_context_views} photos; "
            f"got {len(photos)}. Give {loaded.model.cfg.num_context_views}, or a checkpoint trained with "
            "model.net.view_aggregation: pool (make demo's), which takes any number"
        ) from None
    size, patch = size or loaded.image_size, loaded.patch_size
    if size % patch != 0:
        raise UserError(f"--size {size} is not a multiple of the model's patch size {patch}")
    background = tuple(loaded.background.tolist())
    # Every view shares one model image shape: the first photo's (each other photo centre-cropped to it).
    shape = model_image_shape(*photo_size(photos[0]), size, patch, crop)
    inputs = [load_image(p, size, background, patch=patch, shape=shape) for p in photos]
    images = torch.stack([i.image for i in inputs]).to(device)
    k = (
        None
        if intrinsics is None
        else torch.stack([photo_intrinsics(intrinsics, i) for i in inputs]).to(device)
    )
    try:
        pred = predict_scene(loaded.model, images, k)
    except ValueError as err:  # e.g. more images than the context views the checkpoint was built for
        raise UserError(str(err)) from None
    return PhotoPrediction(loaded, inputs, images, pred, shape)


@torch.no_grad()
def render_views(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [F, 4, 4]
    intrinsics: Tensor,  # [F, 3, 3]
    height: int,
    width: int,
    render_options: dict | None = None,
    chunk: int = 4,
    progress: tqdm | None = None,
) -> Tensor:
    """Render F views of one scene in chunks of ``chunk`` -> colour [F, 3, height, width].

    render_options: keyword arguments of ``aesplat.render.render`` (backend, background, tile_size, ...).
    """
    frames = []
    for start in range(0, extrinsics.shape[0], chunk):
        ext, intr = extrinsics[None, start : start + chunk], intrinsics[None, start : start + chunk]
        out = render(gaussians, ext, intr, height, width, **(render_options or {}))
        frames.append(out.color[0])
        if progress is not None:
            progress.update(out.color.shape[1])
    return torch.cat(frames)
