"""Camera head: refined camera token -> pose relative to view 0 and one field of view per view."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from aesplat.geometry import (
    DEFAULT_FOV,
    homogeneous_to_translation,
    intrinsics_from_fov,
    make_pose,
    rot6d_to_matrix,
)

FOV_MIN = math.radians(10.0)
FOV_MAX = math.radians(160.0)


class CameraHead(nn.Module):
    """An MLP on each refined camera token predicting

    - a 6D rotation (Gram-Schmidt), output bias initialised to the identity;
    - a 4D homogeneous translation t = xyz / (softplus(w) + eps), initialised near zero;
    - one field of view, bounded to [10°, 160°] by a sigmoid and initialised to exactly 2·atan(0.5).

    Poses are camera-to-world in view 0's frame; view 0 is set to the identity exactly (its own camera
    token still tells the transformer which frame is canonical).
    """

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__()
        self.trunk = nn.Sequential(
            nn.LayerNorm(in_dim), nn.Linear(in_dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU()
        )
        self.rotation = nn.Linear(hidden, 6)
        self.translation = nn.Linear(hidden, 4)
        self.fov = nn.Linear(hidden, 1)
        for layer in self.trunk:
            if isinstance(layer, nn.Linear):
                nn.init.trunc_normal_(layer.weight, std=0.02)
                nn.init.zeros_(layer.bias)
        # Small (not zero) pose weights, so cameras depend on the images from the first step.
        nn.init.normal_(self.rotation.weight, std=1e-3)
        nn.init.normal_(self.translation.weight, std=1e-3)
        nn.init.zeros_(self.fov.weight)
        with torch.no_grad():
            self.rotation.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
            self.translation.bias.copy_(torch.tensor([0.0, 0.0, 0.0, math.log(math.e - 1.0)]))  # w -> 1
            frac = (DEFAULT_FOV - FOV_MIN) / (FOV_MAX - FOV_MIN)
            self.fov.bias.fill_(math.log(frac / (1.0 - frac)))

    def forward(self, camera_tokens: Tensor) -> tuple[Tensor, Tensor]:
        """camera_tokens [B, V, C] -> extrinsics [B, V, 4, 4] (camera-to-view-0), intrinsics [B, V, 3, 3]."""
        h = self.trunk(camera_tokens)
        rot = rot6d_to_matrix(self.rotation(h))  # [B, V, 3, 3]
        trans = homogeneous_to_translation(self.translation(h))  # [B, V, 3]
        pose = make_pose(rot, trans)
        eye = torch.eye(4, dtype=pose.dtype, device=pose.device).expand_as(pose[:, :1])
        extrinsics = torch.cat([eye, pose[:, 1:]], dim=1)
        fov = FOV_MIN + (FOV_MAX - FOV_MIN) * torch.sigmoid(self.fov(h)[..., 0])  # [B, V]
        return extrinsics, intrinsics_from_fov(fov)
