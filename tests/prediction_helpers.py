"""A tiny prediction of ``aesplat predict`` with strong view-dependent colour, for the export and viewer tests.

The checkpoint is a random-initialised tiny model (28 x 28 inputs, SH degree 2) whose view-dependent head's
output layer is scaled up: its higher SH bands then change colours by several hundredths, so renders at SH
degree 0 and at degree 2 differ far beyond float tolerance. The two input images are red and blue halves, so
every Gaussian is red or blue.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tests.helpers import IMAGE_SIZE, write_tiny_checkpoint

HEAD_OUTPUT = "model.appearance.view_dependent_head.net.7.weight"
GAUSSIAN_OUTPUT_BIAS = "model.gaussian_head.scratch.output_conv2.2.bias"
DEPTH_OUTPUT_BIAS = "model.depth_head.scratch.output_conv2.2.bias"
RED, BLUE = (220, 30, 30), (30, 30, 220)


def write_view_dependent_checkpoint(run_dir: Path, gain: float = 100.0) -> Path:
    """The tiny checkpoint of the predict tests (RUN/checkpoints/last.ckpt, RUN/config.yaml), its view-dependent
    head's output layer scaled by ``gain`` and its Gaussians made about a pixel wide and opaque (a random-init
    model's are a fiftieth of a pixel and half transparent: invisible in a browser)."""
    torch.manual_seed(0)  # the same model whichever test builds it first
    ckpt = write_tiny_checkpoint(run_dir)
    state = torch.load(ckpt, weights_only=False)
    weights = state["state_dict"]
    weights[HEAD_OUTPUT] = weights[HEAD_OUTPUT] * gain
    bias = weights[GAUSSIAN_OUTPUT_BIAS].clone()  # opacity 0, scale 1..3, rotation 4..7, SH
    bias[1:4] = 35.0  # scales 0.001 * softplus(35) = 0.035: about a pixel at the predicted depth
    bias[0] = 2.0  # opacity 0.88
    weights[GAUSSIAN_OUTPUT_BIAS] = bias
    # the output layers' weights small, so that their biases set every pixel's Gaussian alike: the depth at
    # 0.1 + 19.9 * sigmoid(-2.66) = 1.4 scene units (the depth range of write_tiny_checkpoint), where 0.035 is
    # about a pixel of a 28-pixel view
    for name in (GAUSSIAN_OUTPUT_BIAS, DEPTH_OUTPUT_BIAS):
        weights[name.replace(".bias", ".weight")] = weights[name.replace(".bias", ".weight")] * 0.01
    depth = weights[DEPTH_OUTPUT_BIAS].clone()
    depth[0] = -2.66
    weights[DEPTH_OUTPUT_BIAS] = depth
    torch.save(state, ckpt)
    return ckpt


def split_image(path: Path, boundary: int, size: int = IMAGE_SIZE, width: int | None = None) -> Path:
    """A ``size`` tall, ``width`` (default: ``size``) wide PNG: red left of column ``boundary``, blue after."""
    img = np.empty((size, width or size, 3), np.uint8)
    img[:, :boundary] = RED
    img[:, boundary:] = BLUE
    Image.fromarray(img).save(path)
    return path


def make_prediction(root: Path, *extra: str, width: int = IMAGE_SIZE) -> tuple[Path, Path, list[Path]]:
    """Run ``aesplat predict`` on two split images ``width`` wide -> (prediction folder, checkpoint, images)."""
    from aesplat.predict import main

    ckpt = write_view_dependent_checkpoint(root / "run")
    images = [split_image(root / "left.png", 12, width=width), split_image(root / "right.png", 16, width=width)]
    out = root / "pred"
    argv = ["--ckpt", str(ckpt), "--out", str(out), "--novel-frames", "4", "--no-progress", "--threads", "2"]
    assert main([*argv, *extra, *map(str, images)]) == 0
    return out, ckpt, images
