"""`aesplat predict`: unposed images in; Gaussians (PLY), cameras, re-renders, depth and a novel-view path out.

    aesplat predict --ckpt CKPT --out DIR IMAGE IMAGE [IMAGE ...]

The first image is the reference frame (the world of the outputs), the others follow in the order given.

writes

    DIR/gaussians.ply     one Gaussian per input pixel, reference 3DGS layout (see aesplat.export.ply)
    DIR/cameras.json      predicted camera of every input view (and of every novel frame)
    DIR/inputs/           the images as the model saw them (resized at their aspect ratio, or cropped: see
                          cameras.json, views[].source)
    DIR/renders/          the input views re-rendered from the Gaussians with the predicted cameras
    DIR/depth/            predicted depth per input view: colour-mapped PNG and raw float32 .npy
    DIR/novel/            frames along a path through the predicted input cameras, and trajectory.gif
    DIR/colmap/, DIR/nerfstudio/, DIR/gaussians.splat
                          with ``--export colmap,nerfstudio,splat`` (see aesplat.export; ``aesplat export``
                          writes them from a prediction folder later)

DIR is written whole: into a hidden folder beside it, renamed into place once everything is written (a
failure leaves DIR as it was). A non-empty DIR is refused unless ``--overwrite``, which replaces it as a whole.
A checkpoint trained with ``model.cameras: dataset`` is refused: its camera head never trained, and images
come without poses here. Every refusal is one line (see docs/troubleshooting.md).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import re
import shutil
import socket
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError
from torch import Tensor
from tqdm import tqdm

from .checkpoint import LoadedCheckpoint, load_checkpoint
from .commands import HelpFormatter, OneLineParser, resolve_device
from .errors import MissingFileError, UserError, check_writable, nearest_existing, run_reporting_user_errors
from .export import (
    EXPORTS,
    VIEWER_MAX_SH_DEGREE,
    drop_transparent,
    export_prediction,
    parse_formats,
    write_ply,
)
from .files import Inputs, check_deletable
from .geometry import (
    denormalize_intrinsics,
    focal_to_fov,
    invert_pose,
    make_pose,
    matrix_to_quat,
    quat_to_matrix,
)
from .render import BACKENDS, render
from .threads import ENV_OVERRIDE, apply_thread_policy
from .types import Gaussians

# ---------------------------------------------------------------------------------------------------
# Images in, images out


MAX_UPSCALE = 2  # an image smaller than half the model's input (on either axis) is refused, not blown up
CROPS = ("none", "square")  # the photo's own aspect ratio, or a centre square (the training data's shape)
ORIENTATION = 0x0112  # EXIF tag: how to turn the stored pixels to see the photo upright


@dataclass(frozen=True)
class InputImage:
    """One photo as the model sees it, and what part of the photo that is.

    image   [3, H, W] float in [0, 1], H and W multiples of the model's patch size
    source  (width, height) of the photo in pixels, upright (EXIF orientation applied)
    crop    (left, top, right, bottom) of the photo, in its pixels, that ``image`` shows: the whole photo
            unless its aspect ratio differs from the model image's (a centre crop then)
    """

    image: Tensor
    source: tuple[int, int]
    crop: tuple[float, float, float, float]

    @property
    def cropped(self) -> bool:
        """Whether part of the photo is left out (more than half a source pixel on a side)."""
        w, h = self.source
        left, top, right, bottom = self.crop
        return max(left, top, w - right, h - bottom) > 0.5

    def crop_record(self) -> dict:
        """What ``cameras.json`` says of the photo: its size and the part of it the model saw."""
        return {"width": self.source[0], "height": self.source[1], "crop": [round(c, 2) for c in self.crop],
                "cropped": self.cropped}  # fmt: skip


def model_image_shape(width: int, height: int, size: int, patch: int, crop: str = "none") -> tuple[int, int]:
    """(H, W) of the model image for a photo of ``width`` x ``height``: its shorter side ``size`` (a multiple of
    ``patch``) and its longer side the multiple of ``patch`` nearest to the photo's aspect ratio, so that the
    token grid covers the whole photo with square pixels (what the rounding leaves over, under half a patch,
    is centre-cropped); ``crop="square"``: ``size`` x ``size``."""
    if crop not in CROPS:
        raise UserError(f"unknown crop {crop!r}; choose one of {', '.join(CROPS)}")
    if crop == "square":
        return size, size
    longer = max(size, round(size * max(width, height) / min(width, height) / patch) * patch)
    return (size, longer) if width >= height else (longer, size)


def photo_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, upright (EXIF orientation applied), read from its header only."""
    with _open_image(Path(path)) as img:
        return _upright_size(img)


def load_image(
    path: str | Path,
    size: int,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    patch: int = 14,
    shape: tuple[int, int] | None = None,
    crop: str = "none",
) -> InputImage:
    """Read a photo as the model sees it: resized with square pixels to ``shape`` = (H, W), by default
    ``model_image_shape`` of the photo (its shorter side ``size``, its aspect ratio kept); a photo of another
    aspect ratio than ``shape`` is centre-cropped to it (``InputImage.crop`` says what was kept).

    The photo is decoded reduced where it is much larger than needed (JPEG: in the decoder; other formats: a
    box filter on its 8/16-bit pixels), never as floats at full size. The EXIF orientation is applied first
    (a photo is seen upright). 16-bit and float images keep their full range (scaled, not clipped, to
    [0, 1]). Transparent pixels are composited over ``background`` (the colour the model renders on). A photo
    smaller than half of ``shape`` on either axis is refused. Raises UserError naming the file when it cannot
    be read as an image, is too small, or is over Pillow's decompression-bomb limit.
    """
    path = Path(path)
    try:
        with _open_image(path) as img:
            width, height = _upright_size(img)
            out_h, out_w = shape or model_image_shape(width, height, size, patch, crop)
            scale = max(out_w / width, out_h / height)  # photo pixels -> model pixels, covering the model image
            if scale > MAX_UPSCALE:
                raise UserError(
                    f"input image {str(path)!r} is {width}x{height} pixels, too small for this model's "
                    f"{out_w}x{out_h} input (images are upscaled by at most {MAX_UPSCALE}x): give one of at "
                    f"least {math.ceil(out_w / MAX_UPSCALE)}x{math.ceil(out_h / MAX_UPSCALE)} pixels"
                )
            # Pixels worth decoding: twice the model image's, so that its antialiased resize has some to filter.
            need = (min(width, math.ceil(2 * width * scale)), min(height, math.ceil(2 * height * scale)))
            turned = img.getexif().get(ORIENTATION, 1) in (5, 6, 7, 8)  # stored turned by 90 degrees
            img.draft(img.mode, need[::-1] if turned else need)  # JPEG: decoded at 1/2, 1/4, 1/8; else no-op
            ImageOps.exif_transpose(img, in_place=True)  # in place: no copy of a large decoded photo
            drafted = round(width / img.width)  # the JPEG decoder's whole scale factor (1 without draft)
            img, sixteen_bit, reduced = _reduce(img, need)
            array = _to_rgb_float(img, background, sixteen_bit)
            factor = drafted * reduced  # decoded pixel i covers photo pixels [i·factor, (i + 1)·factor)
    except UserError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise _unreadable(path, err) from None
    # The part of the photo the model image shows, centred: in the photo's pixels, then in the decoded ones.
    box_w, box_h = min(width, out_w / scale), min(height, out_h / scale)  # one of them the photo's own side
    left, top = (width - box_w) / 2, (height - box_h) / 2
    x0, y0 = round(left / factor), round(top / factor)
    x1, y1 = max(x0 + 1, round((left + box_w) / factor)), max(y0 + 1, round((top + box_h) / factor))
    tensor = torch.from_numpy(np.ascontiguousarray(array[y0:y1, x0:x1])).permute(2, 0, 1)[None]  # [1, 3, h, w]
    tensor = torch.nn.functional.interpolate(tensor, size=(out_h, out_w), mode="bicubic", antialias=True,
                                             align_corners=False)  # fmt: skip
    return InputImage(
        tensor[0].clamp(0, 1).contiguous(), (width, height), (left, top, left + box_w, top + box_h)
    )


def _open_image(path: Path) -> Image.Image:
    """``Image.open``; what a user's file can cause is one line: missing, unreadable, a decompression bomb."""
    if not path.is_file():
        raise MissingFileError(f"input image {str(path)!r} does not exist (or is not a file)")
    try:
        return Image.open(path)
    except Image.DecompressionBombError as err:
        raise UserError(
            f"input image {str(path)!r} is refused as a possible decompression bomb ({err}); downscale it first"
        ) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise _unreadable(path, err) from None


def _unreadable(path: Path, err: Exception) -> UserError:
    return UserError(f"cannot read {str(path)!r} as an image ({err}); give PNG/JPEG/... files")


def _upright_size(img: Image.Image) -> tuple[int, int]:
    """(width, height) of an opened image once its EXIF orientation is applied."""
    w, h = img.size
    return (h, w) if img.getexif().get(ORIENTATION, 1) in (5, 6, 7, 8) else (w, h)


def _reduce(img: Image.Image, need: tuple[int, int]) -> tuple[Image.Image, bool, int]:
    """Shrink a decoded image by the largest whole factor that keeps it at least ``need`` = (w, h) (a box
    filter on its own integer pixels); returns it, whether its pixels were 16-bit, and the factor."""
    sixteen_bit = img.mode.startswith("I;16")
    factor = min(img.width // max(1, need[0]), img.height // max(1, need[1]))
    if factor < 2:
        return img, sixteen_bit, 1
    if sixteen_bit:
        img = img.convert("I")  # the box filter takes 32-bit integers, not 16-bit ones
    elif img.mode in ("P", "PA"):
        img = img.convert("RGBA")  # averaging palette indices would mix unrelated colours
    elif img.mode == "1":
        img = img.convert("L")
    return img.reduce(factor), sixteen_bit, factor


def _to_rgb_float(
    img: Image.Image, background: tuple[float, float, float], sixteen_bit: bool = False
) -> np.ndarray:
    """Any PIL image -> float32 [H, W, 3] in [0, 1]: 8-bit, 16-bit (``sixteen_bit``: its pixels were, before a
    conversion to 32-bit) and float modes at their own range, alpha (or a palette's transparency) composited
    over ``background``."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        grey = np.asarray(img, dtype=np.float32)
        sixteen_bit = sixteen_bit or img.mode.startswith("I;16") or grey.max() > 255  # PNG 16-bit opens as I
        peak = 65535.0 if sixteen_bit else 255.0
        return np.repeat((grey / peak).clip(0, 1)[..., None], 3, axis=2).astype(np.float32)
    if img.mode == "F":
        return np.repeat(np.asarray(img, dtype=np.float32).clip(0, 1)[..., None], 3, axis=2)
    if img.mode == "P" and "transparency" in img.info or img.mode in ("PA", "LA", "La", "RGBa"):
        img = img.convert("RGBA")
    if img.mode == "RGBA":
        rgba = np.asarray(img, dtype=np.float32) / 255.0
        alpha = rgba[..., 3:]
        return rgba[..., :3] * alpha + np.asarray(background, dtype=np.float32) * (1.0 - alpha)
    return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0


def to_uint8(image: Tensor) -> np.ndarray:
    """A [3, H, W] float image in [0, 1] as uint8 [H, W, 3] (rounded), on the CPU."""
    return (image.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()


def save_image(image: Tensor, path: Path) -> None:
    """Write a [3, H, W] float image in [0, 1] as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(to_uint8(image)).save(path)


def colorize_depth(depth: Tensor, cmap: str = "turbo") -> np.ndarray:
    """Depth [H, W] -> colour-mapped uint8 [H, W, 3]; near is warm, far is cool (robust 2-98 % range)."""
    from matplotlib import colormaps

    d = depth.detach().float().cpu()
    valid = d > 0
    if not bool(valid.any()):
        return np.zeros((*d.shape, 3), dtype=np.uint8)
    lo, hi = torch.quantile(d[valid], torch.tensor([0.02, 0.98])).tolist()
    t = ((hi - d) / max(hi - lo, 1e-8)).clamp(0, 1)  # 1 = near
    rgb = colormaps[cmap](t.numpy())[..., :3]
    rgb[~valid.numpy()] = 0.0
    return (rgb * 255).round().astype(np.uint8)


# ---------------------------------------------------------------------------------------------------
# Cameras


def slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Spherical interpolation of unit quaternions (w, x, y, z): q0, q1 [F, 4] at times t [F] -> [F, 4]."""
    dot = (q0 * q1).sum(-1, keepdim=True)  # [F, 1]
    q1 = torch.where(dot < 0, -q1, q1)  # the shorter way round
    theta = torch.acos(dot.abs().clamp(max=1.0))
    t = t[:, None]
    near = theta < 1e-4  # nearly equal rotations: linear interpolation, no 0 / 0
    sin = torch.where(near, torch.ones_like(theta), torch.sin(theta))
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / sin)
    w1 = torch.where(near, t, torch.sin(t * theta) / sin)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_cameras(extrinsics: Tensor, intrinsics: Tensor, frames: int) -> tuple[Tensor, Tensor]:
    """A path through V cameras in order: extrinsics [V, 4, 4] (camera-to-world), intrinsics [V, 3, 3].

    Rotations are slerped, centres and intrinsics interpolated linearly, ``frames`` poses in all (the first
    and last are the first and last input cameras). Returns extrinsics [F, 4, 4] and intrinsics [F, 3, 3].
    """
    v = extrinsics.shape[0]
    if v < 2:
        raise ValueError("a camera path needs at least two cameras")
    if frames < 2:
        raise ValueError(f"a camera path needs at least two frames, got {frames}")
    s = torch.linspace(0, v - 1, frames, dtype=extrinsics.dtype, device=extrinsics.device)  # [F]
    seg = s.floor().long().clamp(max=v - 2)
    t = s - seg  # [F] position within the segment
    quats = matrix_to_quat(extrinsics[:, :3, :3])  # [V, 4]
    rots = quat_to_matrix(slerp(quats[seg], quats[seg + 1], t))  # [F, 3, 3]
    centres = extrinsics[:, :3, 3]
    tt = t[:, None]
    trans = (1 - tt) * centres[seg] + tt * centres[seg + 1]  # [F, 3]
    tk = t[:, None, None]
    intr = (1 - tk) * intrinsics[seg] + tk * intrinsics[seg + 1]  # [F, 3, 3]
    return make_pose(rots, trans), intr


def compact_json(obj: object) -> str:
    """JSON with two-space indents but each innermost list of numbers (a matrix row) on one line."""
    text = json.dumps(obj, indent=2)
    numbers = re.compile(r"\[([-0-9.eE+,\s]+)\]")
    return numbers.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)


def camera_record(extrinsics: Tensor, intrinsics: Tensor, height: int, width: int) -> dict:
    """A JSON-able description of one camera: c2w / w2c 4x4, normalised and pixel 3x3 intrinsics, FOVs."""
    k_pix = denormalize_intrinsics(intrinsics, height, width)
    fov_x = focal_to_fov(intrinsics[0, 0]).item()
    fov_y = focal_to_fov(intrinsics[1, 1]).item()
    return {
        "camera_to_world": extrinsics.tolist(),
        "world_to_camera": invert_pose(extrinsics).tolist(),
        "intrinsics_normalized": intrinsics.tolist(),
        "intrinsics_pixels": k_pix.tolist(),
        "width": width,
        "height": height,
        "fov_x_deg": math.degrees(fov_x),
        "fov_y_deg": math.degrees(fov_y),
    }


# ---------------------------------------------------------------------------------------------------
# Prediction


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
def predict_scene(model: torch.nn.Module, images: Tensor) -> Prediction:
    """Run the model on context images [V, 3, H, W] (float in [0, 1], on the model's device)."""
    out = model(images[None], None)
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


def predict_photos(
    ckpt: str | Path, photos: list[str], *, size: int | None, crop: str, device: torch.device
) -> PhotoPrediction:
    """Load ``ckpt`` and predict from ``photos`` (the first is the reference frame; every view takes the first
    photo's shape, ``size`` its shorter side, default the trained size; ``crop`` as ``--crop``). A checkpoint
    without a camera head, a count its appearance head cannot take or a size its patch does not divide is one
    line (UserError) before any photo is read."""
    loaded = load_checkpoint(ckpt, device)
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
    try:
        pred = predict_scene(loaded.model, images)
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


def write_outputs(
    out_dir: Path,
    names: list[str],
    images: Tensor,  # [V, 3, H, W]
    pred: Prediction,
    *,
    novel_frames: int,
    ply_sh_degree: int | None,
    min_opacity: float,
    render_options: dict | None = None,
    progress: bool = True,
    sources: list[dict] | None = None,
) -> dict:
    """Render and write every output of ``aesplat predict`` under ``out_dir``; returns the cameras record.
    ``sources``: per view, what part of which photo the model saw (``InputImage.crop_record``)."""
    v, _, height, width = images.shape
    steps = 2 * v + novel_frames + 2  # inputs+depth, re-renders, novel frames, PLY, cameras
    bar = tqdm(total=steps, desc="aesplat predict", unit="step", disable=not progress)
    for i in range(v):
        save_image(images[i], out_dir / "inputs" / f"{i:02d}_{names[i]}.png")
        (out_dir / "depth").mkdir(parents=True, exist_ok=True)
        np.save(out_dir / "depth" / f"{i:02d}_{names[i]}.npy", pred.depth[i].cpu().numpy().astype(np.float32))
        Image.fromarray(colorize_depth(pred.depth[i])).save(out_dir / "depth" / f"{i:02d}_{names[i]}.png")
        bar.update(1)
    renders = render_views(pred.gaussians, pred.extrinsics, pred.intrinsics, height, width, render_options,
                           progress=bar)  # fmt: skip
    for i in range(v):
        save_image(renders[i], out_dir / "renders" / f"{i:02d}_{names[i]}.png")
    novel_ext, novel_int = interpolate_cameras(pred.extrinsics, pred.intrinsics, novel_frames)
    novel = render_views(pred.gaussians, novel_ext, novel_int, height, width, render_options, progress=bar)
    for f in range(novel_frames):
        save_image(novel[f], out_dir / "novel" / f"{f:03d}.png")
    frames = [Image.open(out_dir / "novel" / f"{f:03d}.png") for f in range(novel_frames)]
    frames += frames[-2:0:-1]  # there and back again
    frames[0].save(
        out_dir / "novel" / "trajectory.gif", save_all=True, append_images=frames[1:], duration=80, loop=0
    )

    gaussians = drop_transparent(pred.gaussians, min_opacity)
    degree = min(gaussians.sh_degree, VIEWER_MAX_SH_DEGREE) if ply_sh_degree is None else ply_sh_degree
    write_ply(out_dir / "gaussians.ply", gaussians, sh_degree=degree)
    bar.update(1)
    cameras = {
        "convention": "OpenCV axes (x right, y down, z forward); world = the first input view's camera frame; "
        "intrinsics_normalized has fx, cx divided by width and fy, cy by height",
        "views": [
            {
                "image": names[i],
                **camera_record(pred.extrinsics[i].cpu(), pred.intrinsics[i].cpu(), height, width),
                **({"source": sources[i]} if sources else {}),
            }
            for i in range(v)
        ],
        "novel": [
            camera_record(novel_ext[f].cpu(), novel_int[f].cpu(), height, width) for f in range(novel_frames)
        ],
        "gaussians": {"count": gaussians.num_gaussians, "ply_sh_degree": degree, "min_opacity": min_opacity},
        # what the renders were made with, so that a viewer renders the same images from these files
        "render": _render_record(render_options),
    }
    (out_dir / "cameras.json").write_text(compact_json(cameras))
    bar.update(1)
    bar.close()
    return cameras


def _render_record(render_options: dict | None) -> dict:
    """The background and renderer options of ``render_options`` as JSON (the backend is the machine's)."""
    options = dict(render_options or {})
    background = options.pop("background", None)
    options.pop("backend", None)
    background = [0.0, 0.0, 0.0] if background is None else torch.as_tensor(background).tolist()
    return {"background": background, "options": options}


# ---------------------------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="aesplat predict",
        description="Predict cameras and 3D Gaussians from unposed images with a trained checkpoint; write a "
        "3DGS PLY, the cameras, re-renders of the inputs, depth maps and a short novel-view path.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="2 or more images of one scene; the first is the reference frame, the others "
                        "follow in the order given (a model with the paper's appearance head, "
                        "view_aggregation concat, takes exactly the count it was built for, 2; a pool model "
                        "any); photos keep their aspect ratio (that of the first; others are centre-cropped "
                        "to it); any size down to half the model's input; 16-bit images keep their range, "
                        "transparent pixels are composited over the model's background colour, EXIF "
                        "orientation is applied")  # fmt: skip
    parser.add_argument("--ckpt", required=True, help="checkpoint written by `aesplat fit` (last.ckpt / best)")
    parser.add_argument("--out", required=True,
                        help="output folder: created whole (written beside it, then renamed into place); an "
                        "existing non-empty folder is refused unless --overwrite")  # fmt: skip
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a non-empty --out folder as a whole (its old contents are removed)",
    )
    parser.add_argument("--size", type=int, default=None,
                        help="the shorter side of the model's input, a multiple of the model's patch size; the "
                        "longer side follows the photo's aspect ratio (default: the image size the checkpoint "
                        "was trained at)")  # fmt: skip
    parser.add_argument("--crop", choices=CROPS, default="none",
                        help="none: the photo's own aspect ratio; square: a centre square, the shape the "
                        "models are trained on (cameras.json says what was cropped)")  # fmt: skip
    parser.add_argument("--novel-frames", type=int, default=30, help="frames of the novel-view path")
    parser.add_argument("--ply-sh-degree", type=int, default=None,
                        help="SH bands written to the PLY (default: min(model degree, 3), what common 3DGS "
                        "viewers read)")  # fmt: skip
    parser.add_argument("--min-opacity", type=float, default=0.0,
                        help="leave Gaussians below this opacity out of the PLY")  # fmt: skip
    parser.add_argument("--export", default=None, metavar="FORMATS",
                        help="also write these exports, comma-separated: colmap (DIR/colmap/), "
                        "nerfstudio (DIR/nerfstudio/), splat (DIR/gaussians.splat); see `aesplat export "
                        "--help`")  # fmt: skip
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:1, ... (auto: cuda if available)")
    parser.add_argument("--backend", default="auto", help="renderer backend: auto, torch or gsplat")
    parser.add_argument("--threads", type=int, default=None,
                        help=f"torch CPU threads (default: the usable cores, or ${ENV_OVERRIDE})")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def check_output_dir(out: Path, overwrite: bool, inputs: Inputs = ()) -> None:
    """Refuse, before anything is loaded, an output folder that cannot be written whole: a file, a folder that
    holds something (unless ``overwrite``; and never one that holds the current folder, the home folder or one
    of the command's ``inputs``), or a place without write permission."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a folder; give a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise UserError(
            f"--out {out} is not empty; give a new folder, or --overwrite to replace it (as a whole)"
        )
    if out.is_dir():  # it is replaced as a whole, even empty
        check_deletable(out, "--overwrite" if overwrite else "--out", inputs)
    check_writable(out.resolve().parent, f"--out {out}")  # the folder is renamed into place beside it


def _staging_prefix(out: Path, pid: int | str = "") -> str:
    """Name prefix of the staging folders of ``out`` made on this machine (by process ``pid``)."""
    return f".{out.name}.partial-{socket.gethostname()}-{pid}"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_staging(out: Path) -> list[Path]:
    """The staging folders of ``out`` left by earlier runs on this machine whose process is gone (killed
    outright, ``kill -9`` or a power loss: a stop signal removes its own); removed, and returned. Another
    machine's (a shared file system) and running processes' are left alone."""
    prefix = _staging_prefix(out)
    stale = []
    for path in out.parent.glob(glob.escape(prefix) + "*"):
        pid = path.name[len(prefix) :].split("-", 1)[0]
        if pid.isdigit() and path.is_dir() and not _running(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            stale.append(path)
    return stale


@contextmanager
def staged_output(out: Path, overwrite: bool):
    """Yield a temporary folder beside ``out``; when the block ends without error, it becomes ``out`` (an old
    ``out``, allowed by ``overwrite``, is removed as a whole); on error it is deleted and ``out`` untouched.
    Its name holds this machine's name and this process's id, so that a later run removes it when the
    process was killed outright (:func:`remove_stale_staging`)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    for path in remove_stale_staging(out):
        print(f"aesplat predict: removed {path}, the staging folder of an earlier run that was killed")
    staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(out, os.getpid()) + "-", dir=out.parent))
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    old = None
    if out.exists():
        if any(out.iterdir()) and not overwrite:  # something appeared there while we worked
            shutil.rmtree(staging, ignore_errors=True)
            raise UserError(f"--out {out} was filled by something else meanwhile; nothing was written")
        old = out.parent / f".{out.name}.old-{staging.name.rsplit('-', 1)[-1]}"
        os.replace(out, old)
    os.replace(staging, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat predict`` (see ``--help``)."""
    args = build_parser().parse_args(argv)
    return run_reporting_user_errors("predict", lambda: _predict(args))


def check_options(args: argparse.Namespace) -> None:
    """Every option's value, checked before anything is loaded or written (one line each)."""
    if len(args.images) < 2:
        raise UserError("give at least two images of the same scene")
    if args.novel_frames < 2:
        raise UserError("--novel-frames must be at least 2")
    if args.size is not None and args.size < 1:
        raise UserError(f"--size must be a positive number of pixels, got {args.size}")
    if args.ply_sh_degree is not None and args.ply_sh_degree < 0:
        raise UserError(f"--ply-sh-degree must be 0 or more, got {args.ply_sh_degree}")
    if not 0.0 <= args.min_opacity < 1.0:
        raise UserError(f"--min-opacity must be in [0, 1), got {args.min_opacity}")
    if args.backend != "auto" and args.backend not in BACKENDS:
        raise UserError(f"--backend {args.backend} is not a renderer: give auto, {', '.join(BACKENDS)}")


def check_name_lengths(out: Path, photos: list[str], names: list[str]) -> None:
    """Refuse, before the model loads, a photo whose outputs' file name (``inputs/NN_NAME.png``, the longest)
    is longer than the file system under ``out`` allows."""
    try:
        limit = os.pathconf(nearest_existing(out.resolve().parent), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for i, (photo, name) in enumerate(zip(photos, names)):
        length = len(os.fsencode(f"{i:02d}_{name}.png"))
        if length > limit:
            raise UserError(f"the input image {photo!r} makes a {length}-byte file name under --out (this file "
                            f"system allows {limit}); rename the photo")  # fmt: skip


def _predict(args: argparse.Namespace) -> int:
    apply_thread_policy(num_workers=0, override=args.threads)
    check_options(args)
    out_dir = Path(args.out)
    inputs = [("--ckpt", args.ckpt), *(("the input image", image) for image in args.images)]
    check_output_dir(out_dir, args.overwrite, inputs)
    names = [Path(p).stem for p in args.images]
    check_name_lengths(out_dir, args.images, names)
    exports = parse_formats(args.export) if args.export is not None else []
    device = resolve_device(args.device)
    photos = predict_photos(args.ckpt, args.images, size=args.size, crop=args.crop, device=device)
    loaded, inputs, images, pred, shape = photos.loaded, photos.inputs, photos.images, photos.pred, photos.shape
    model_degree = loaded.sh_degree
    if args.ply_sh_degree is not None and not 0 <= args.ply_sh_degree <= model_degree:
        raise UserError(f"--ply-sh-degree must be in 0..{model_degree} for this checkpoint")
    options = {**loaded.render_options(device), "backend": args.backend}
    with staged_output(out_dir, args.overwrite) as staging:
        write_outputs(
            staging, names, images, pred, novel_frames=args.novel_frames, ply_sh_degree=args.ply_sh_degree,
            min_opacity=args.min_opacity, render_options=options, progress=not args.no_progress,
            sources=[i.crop_record() for i in inputs],
        )  # fmt: skip
        export_prediction(staging, exports)
    written = "".join(", " + EXPORTS[name].dest for name in exports)
    print(f"aesplat predict: {len(inputs)} views of {shape[1]}x{shape[0]} pixels; wrote "
          f"{out_dir / 'gaussians.ply'} ({pred.gaussians.num_gaussians:,} Gaussians), cameras.json, inputs/, "
          f"renders/, depth/, novel/{written} under {out_dir}")  # fmt: skip
    for name, i in zip(names, inputs):
        if i.cropped:
            left, top, right, bottom = (round(c) for c in i.crop)
            print(f"aesplat predict: {name!r} ({i.source[0]}x{i.source[1]}) was centre-cropped to its pixels "
                  f"x {left}..{right}, y {top}..{bottom} (cameras.json: views[].source)")  # fmt: skip
    return 0
