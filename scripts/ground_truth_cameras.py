#!/usr/bin/env python
"""Diagnostic: train or test with the ground-truth relative poses in place of the camera head's.

    python scripts/ground_truth_cameras.py fit -c conf/demo.yaml [--key value ...]
    python scripts/ground_truth_cameras.py test -c conf/demo.yaml --ckpt_path RUN/checkpoints/last.ckpt

The arguments are those of ``aesplat fit|validate|test``. This is not the method: AESplat never sees a
ground-truth pose in training. It separates what the pose head has to learn from what the depth and Gaussian
heads learn: if a run with ground-truth poses reaches a much higher PSNR than the normal one, the poses are the
bottleneck. The camera head still runs (its intrinsics are kept); every view's camera-to-world pose is
replaced by the data set's, relative to context view 0. Checkpoints written this way load only through this
script.
"""

from __future__ import annotations

import sys

import torch
from torch import Tensor, nn

from aesplat.cli import run_lightning
from aesplat.geometry import relative_to_first
from aesplat.train import AESplatModule
from aesplat.types import BatchedExample


class PosesFromBatch(nn.Module):
    """Wraps a camera head: keeps its intrinsics, returns the poses set for the current batch."""

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head
        self.poses: Tensor | None = None

    def forward(self, camera_tokens: Tensor) -> tuple[Tensor, Tensor]:
        extrinsics, intrinsics = self.head(camera_tokens)
        if self.poses is None:
            raise RuntimeError("no ground-truth poses set for this forward pass")
        return self.poses.to(extrinsics), intrinsics


class GroundTruthCamerasModule(AESplatModule):
    """AESplatModule whose renders and Gaussians use the ground-truth relative poses of each batch."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.model.camera_head = PosesFromBatch(self.model.camera_head)

    def forward(self, batch: BatchedExample):
        poses = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1)
        self.model.camera_head.poses = relative_to_first(poses.float())
        try:
            return super().forward(batch)
        finally:
            self.model.camera_head.poses = None


if __name__ == "__main__":
    run_lightning(sys.argv[1:], module_class=GroundTruthCamerasModule)
