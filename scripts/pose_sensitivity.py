#!/usr/bin/env python
"""Diagnostic: how much a trained model's renders depend on the target pose, and whether the photometric loss
at the model's own poses points towards the true rotation.

    python scripts/pose_sensitivity.py --ckpt RUN/checkpoints/last.ckpt --data-root outputs/demo/shards \
        [--image-size 42 --scenes 12 --offsets -8 -4 -2 -1 0 1 2 4 8 --step 1 --out sensitivity.json]

For each target view of the first ``--scenes`` test scenes it measures

1. **Yaw landscape**: PSNR of the render when every view has the data set's camera (pose relative to context
   view 0, and intrinsics), except that the target's camera is turned about its own y axis by each offset
   (degrees). A steep peak at 0 says how precisely the camera head must predict rotation before sharp
   renders pay off.
2. **Downhill agreement**: with the model's own predicted cameras, the target's loss at yaw +/- ``--step``
   degrees. The loss "points the right way" when it falls towards the ground-truth yaw. If that holds for
   about half of the views, the photometric gradient on rotation is noise at this state of the model.

Works with checkpoints of ``aesplat fit`` with either ``model.cameras``. The camera head of a
``model.cameras: dataset`` checkpoint never trained; its downhill figures describe that untrained head.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch
from torch import Tensor

from aesplat.data import DataModule
from aesplat.model import forward_batch
from aesplat.render import render
from aesplat.train import AESplatModule


def load_module(path: str | Path) -> AESplatModule:
    """The AESplatModule of an ``aesplat fit`` checkpoint, on the CPU, in eval mode."""
    # Only MSE is measured: no VGG weights needed.
    module = AESplatModule.load_from_checkpoint(path, map_location="cpu", loss={"lpips_weight": 0.0},
                                                eval={"metrics_lpips": False})  # fmt: skip
    return module.eval()


def yaw_rotation(degrees: float) -> Tensor:
    """Rotation [3, 3] about the camera's y axis (down) by ``degrees``."""
    a = math.radians(degrees)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def relative_yaw(pose: Tensor, reference: Tensor) -> float:
    """Yaw (degrees) of camera-to-world ``reference`` [4, 4] seen from ``pose`` [4, 4] (about pose's y axis)."""
    rel = pose[:3, :3].T @ reference[:3, :3]
    return math.degrees(math.atan2(rel[0, 2].item(), rel[0, 0].item()))


def turn_yaw(pose: Tensor, degrees: float) -> Tensor:
    """Camera-to-world ``pose`` [..., 4, 4] turned about its own y axis by ``degrees``."""
    turned = pose.clone()
    turned[..., :3, :3] = pose[..., :3, :3] @ yaw_rotation(degrees)
    return turned


def _mse(module: AESplatModule, gaussians, extrinsics: Tensor, intrinsics: Tensor, image: Tensor) -> float:
    h, w = image.shape[-2:]
    background = torch.tensor(module.render_cfg.background)
    out = render(gaussians, extrinsics, intrinsics, h, w, background=background, backend="torch")
    return ((out.color[:, 0] - image) ** 2).mean().item()


@torch.no_grad()
def measure(module: AESplatModule, batches, offsets: list[float], step: float = 1.0) -> dict:
    """The two measurements over ``batches`` (eval batches of one scene each); see the module docstring."""
    landscape, downhill = [], []
    for batch in batches:
        batch = module.on_after_batch_transfer(batch, 0)
        vc = batch.context.num_views
        own = forward_batch(module.model, batch, "predicted")  # the camera head's cameras
        true = forward_batch(module.model, batch, "dataset")
        truth = true.extrinsics  # [B, Vc + Vt, 4, 4] the data set's poses relative to context view 0
        for t in range(batch.target.num_views):
            v, image = vc + t, batch.target.images[:, t]
            landscape.append([_mse(module, true.gaussians, turn_yaw(truth[:, v : v + 1], d),
                                   true.intrinsics[:, v : v + 1], image) for d in offsets])  # fmt: skip
            pose = own.extrinsics[:, v : v + 1]
            error = relative_yaw(pose[0, 0], truth[0, v])
            minus, plus = (_mse(module, own.gaussians, turn_yaw(pose, d), own.intrinsics[:, v : v + 1], image)
                           for d in (-step, step))  # fmt: skip
            downhill.append({"yaw_error_deg": error, "loss_minus": minus, "loss_plus": plus,
                             "agrees": (plus < minus) == (error > 0)})  # fmt: skip
    psnr = -10.0 * torch.log10(torch.tensor(landscape).clamp_min(1e-10))
    return {
        "offsets_deg": offsets,
        "landscape_psnr": psnr.mean(0).tolist(),
        "views": len(downhill),
        "downhill_agrees": sum(d["agrees"] for d in downhill),
        "downhill": downhill,
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ckpt", required=True, help="checkpoint of aesplat fit (either model.cameras)")
    p.add_argument("--data-root", required=True, help="shard folder with test/ (data_prep/to_shards.py)")
    p.add_argument("--image-size", type=int, default=42, help="model input size (default 42, the demo's)")
    p.add_argument("--scenes", type=int, default=12, help="test scenes to use (default 12)")
    p.add_argument("--offsets", type=float, nargs="+", default=[-8, -4, -2, -1, 0, 1, 2, 4, 8],
                   help="yaw offsets of the landscape, degrees")  # fmt: skip
    p.add_argument("--step", type=float, default=1.0, help="yaw step of the downhill test, degrees (default 1)")
    p.add_argument("--out", type=Path, default=None, help="also write the figures to this JSON file")
    a = p.parse_args(argv)
    if a.scenes < 1 or a.step <= 0:
        p.error("--scenes must be >= 1 and --step > 0")
    module = load_module(a.ckpt)
    data = DataModule(root=a.data_root, image_size=a.image_size, num_workers=0, eval_batch_size=1)
    batches = (b for i, b in zip(range(a.scenes), data.test_dataloader()))
    result = measure(module, batches, list(a.offsets), a.step)
    print("yaw offset (deg) | " + " | ".join(f"{d:g}" for d in result["offsets_deg"]))
    print("PSNR (dB)        | " + " | ".join(f"{v:.2f}" for v in result["landscape_psnr"]))
    print(f"downhill agreement at the model's own poses: {result['downhill_agrees']}/{result['views']} views")
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
