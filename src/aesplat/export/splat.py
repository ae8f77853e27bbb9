"""Gaussians to a ``.splat`` file: the compact layout web splat viewers load (antimatter15's format).

32 bytes per Gaussian, little endian, no header:

    bytes  0-11   centre x, y, z                    3 x float32
    bytes 12-23   standard deviations sx, sy, sz    3 x float32 (linear, not log)
    bytes 24-27   base colour R, G, B and opacity   4 x uint8 (colour = SH DC + 0.5, clipped to [0, 1])
    bytes 28-31   rotation w, x, y, z               4 x uint8, q * 128 + 128 clipped to [0, 255]

Only the base colour survives: the format has no view-dependent SH. Centres and scales are exact (float32);
colour, opacity and rotation are quantised to 8 bits (rotation components to 1/128).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..geometry import safe_unit_quat, sh_dc_to_rgb
from ..types import Gaussians

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])


def gaussians_to_splat_array(gaussians: Gaussians, index: int = 0) -> np.ndarray:
    """The ``.splat`` records [N] (``SPLAT_DTYPE``) of scene ``index`` of a batch, in the Gaussians' order."""
    g = gaussians.detach().to("cpu", torch.float32)
    n = g.num_gaussians
    rgb = sh_dc_to_rgb(g.sh[index, :, 0]).clamp(0, 1)  # [N, 3]
    rgba = torch.cat([rgb, g.opacities[index, :, None].clamp(0, 1)], dim=1)  # [N, 4]
    quats = safe_unit_quat(g.quats[index])  # [N, 4] (w, x, y, z); a zero quaternion becomes the identity
    records = np.zeros(n, dtype=SPLAT_DTYPE)
    records["position"] = g.means[index].numpy()
    records["scale"] = g.scales[index].numpy()
    records["rgba"] = (rgba * 255).round().numpy().astype(np.uint8)
    records["rotation"] = (quats * 128 + 128).round().clamp(0, 255).numpy().astype(np.uint8)
    return records


def write_splat(path: str | Path, gaussians: Gaussians, index: int = 0) -> Path:
    """Write scene ``index`` of ``gaussians`` to ``path`` as ``.splat``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(gaussians_to_splat_array(gaussians, index).tobytes())
    return path
