"""Images in and out: a photo as the model sees it (``load_image``), a float image as PNG (``save_image``), a
depth map colour-mapped (``colorize_depth``).

A photo is seen upright (EXIF orientation applied), at its own aspect ratio or centre-cropped
(``model_image_shape``), decoded reduced where it is much larger than needed; what a user's file can cause
(missing, unreadable, too small, a decompression bomb) is one line naming the file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError
from torch import Tensor

from .errors import MissingFileError, UserError

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
