"""The browser's viewpoint as a pinhole camera of this project, and back.

viser reports each client's camera as an orientation ``wxyz`` and a ``position`` (camera-to-world, OpenCV
axes: x right, y down, z forward, as here), a vertical field of view and the canvas aspect ratio. A viewpoint
has square pixels and a centred principal point, so a predicted camera (equal horizontal and vertical field
of view, centred) of a square image converts both ways exactly.

A browser reports its canvas size as it likes, and a render's size follows it: :func:`capped_height` and
:func:`capped_aspect` bound what a client can make the server render.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry import make_pose, matrix_to_quat, quat_to_matrix

MAX_ASPECT = 4.0  # a client's view is rendered at most 4 times as wide as tall (or as tall as wide)


@dataclass(frozen=True)
class Viewpoint:
    """A browser camera: wxyz (4,) rotation camera-to-world (w, x, y, z), position (3,) its centre, fov the
    vertical field of view in radians, aspect the image width over its height."""

    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov: float
    aspect: float

    def extrinsics(self) -> Tensor:
        """Camera-to-world [4, 4] float32."""
        rot = quat_to_matrix(torch.tensor(self.wxyz, dtype=torch.float64))
        return make_pose(rot, torch.tensor(self.position, dtype=torch.float64)).float()

    def size(self, height: int) -> tuple[int, int]:
        """(height, width) of an image ``height`` pixels tall at this aspect ratio."""
        return height, max(1, round(height * self.aspect))

    def intrinsics(self, height: int) -> Tensor:
        """Normalised intrinsics [3, 3] float32 of the ``size(height)`` image: square pixels, centred."""
        h, w = self.size(height)
        fy = 0.5 / math.tan(0.5 * self.fov)  # normalised by the height
        return torch.tensor([[fy * h / w, 0.0, 0.5], [0.0, fy, 0.5], [0.0, 0.0, 1.0]], dtype=torch.float32)


def viewpoint_of(extrinsics: Tensor, intrinsics: Tensor, width: int, height: int) -> Viewpoint:
    """A camera (camera-to-world [4, 4], normalised intrinsics [3, 3], image size) as a browser viewpoint: its
    pose, its vertical field of view and its aspect ratio."""
    ext = extrinsics.double()
    wxyz = matrix_to_quat(ext[:3, :3]).tolist()
    fov = 2.0 * math.atan(0.5 / float(intrinsics[1, 1]))
    return Viewpoint(tuple(wxyz), tuple(ext[:3, 3].tolist()), fov, width / height)


def capped_aspect(width: float, height: float) -> float:
    """The aspect ratio (width / height) of a browser's canvas as the server renders it: within
    1 / MAX_ASPECT .. MAX_ASPECT, and 1 for a size that is not two positive numbers. A render's width is its
    height times this, so a client cannot ask for an image of any width."""
    if not (width > 0 and height > 0):  # also false for NaN
        return 1.0
    aspect = width / height
    if not math.isfinite(aspect):
        return 1.0
    return min(max(aspect, 1.0 / MAX_ASPECT), MAX_ASPECT)


def capped_height(height: float, most: int) -> int:
    """The pixel height of a render of a browser's canvas ``height`` pixels tall: at most ``most``, at
    least 1."""
    if not height > 0:  # also false for NaN
        return 1
    return max(1, int(min(height, most)))
