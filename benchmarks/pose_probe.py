#!/usr/bin/env python
"""Supervised relative-pose probe: can a network of this size learn the views' relative rotation at all?

    python benchmarks/pose_probe.py [--data outputs/warmstart] [--variants head head-correlation stacked-cnn]
        [--steps 2000 --batch 8 --lr 1e-3 --every 250] [--out outputs/pose-probe]

Trains only a pose regressor, with the data set's relative cameras as labels (no rendering, no Gaussians):
10 x the geodesic rotation angle (radians) + the L1 translation distance (``aesplat.train.loss.camera_loss``),
AdamW, gradient norm clipped to 1, one thread. Every ``--every`` steps it reports the mean rotation error of
the last training batches and the rotation error on every held-out test view (the shards' test split, all
targets). Predicting no rotation scores the mean true angle, which the table prints beside.

Variants:
    head              the model's encoder, geometry transformer and camera head (``tiny``, patch 14), as the
                      method predicts cameras
    head-correlation  the same with ``camera_correlation``: the head also sees a view-0 cost volume
    stacked-cnn       a four-layer CNN on view 0 and view i stacked channel-wise, pooled, then a linear pose

Writes OUT/<variant>.csv (step, train_rot_deg, test_rot_deg, seconds) and OUT/PROBE.md. The data: shards
made like the warm start's (``learning_curves.py`` makes them: synthetic.py --seed 1 --scenes 96
--test-scenes 8 at 42 px), created under DATA when missing.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import torch
from torch import Tensor, nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

VARIANTS = ("head", "head-correlation", "stacked-cnn")


class StackedPairCNN(nn.Module):
    """View 0 and view i stacked as 6 channels -> a 6D rotation and a translation for view i."""

    def __init__(self, width: int = 32) -> None:
        super().__init__()
        c = width
        self.net = nn.Sequential(
            nn.Conv2d(6, c, 3, 1, 1), nn.GELU(), nn.Conv2d(c, c, 3, 2, 1), nn.GELU(),
            nn.Conv2d(c, 2 * c, 3, 2, 1), nn.GELU(), nn.Conv2d(2 * c, 2 * c, 3, 2, 1), nn.GELU(),
            nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(2 * c, 128), nn.GELU(),
        )  # fmt: skip
        self.rotation, self.translation = nn.Linear(128, 6), nn.Linear(128, 3)
        nn.init.zeros_(self.rotation.weight)
        nn.init.zeros_(self.translation.weight)
        with torch.no_grad():
            self.rotation.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))

    def forward(self, images: Tensor) -> Tensor:
        """images [B, V, 3, H, W] -> extrinsics [B, V, 4, 4] relative to view 0 (view 0 the identity)."""
        from aesplat.geometry import make_pose, rot6d_to_matrix

        b, v = images.shape[:2]
        pairs = torch.cat([images[:, :1].expand(-1, v - 1, -1, -1, -1), images[:, 1:]], dim=2).flatten(0, 1)
        h = self.net(pairs)
        pose = make_pose(rot6d_to_matrix(self.rotation(h)), self.translation(h)).unflatten(0, (b, v - 1))
        return torch.cat([torch.eye(4).expand(b, 1, 4, 4), pose], dim=1)


def pose_regressor(variant: str):
    """(trainable module, images [B, V, 3, H, W] -> extrinsics [B, V, 4, 4]) for a variant."""
    from aesplat.model import build_model

    if variant == "stacked-cnn":
        net = StackedPairCNN()
        return net, net
    model = build_model("tiny", camera_correlation=variant == "head-correlation")

    def predict(images: Tensor) -> Tensor:
        layers = model.aggregator(images, num_context=images.shape[1])
        return model.camera_head(layers[-1][:, :, 0], images)[0]

    keep = nn.ModuleList([model.aggregator, model.camera_head])  # the DPT heads are unused
    return keep, predict


def all_views(batch) -> Tensor:
    return torch.cat([batch.context.images, batch.target.images], dim=1)


def probe(variant: str, args: argparse.Namespace, shards: Path) -> list[dict]:
    from aesplat.data import DataModule
    from aesplat.model import dataset_cameras
    from aesplat.train.loss import camera_loss
    from aesplat.train.metrics import relative_pose_errors

    torch.manual_seed(args.seed)
    data = DataModule(root=str(shards), image_size=args.size, batch_size=args.batch, num_workers=1,
                      gap_initial=(5, 21), gap_final=(5, 21), gap_warmup_steps=1,
                      train_batches_per_epoch=10**9, seed=args.seed)  # fmt: skip
    data.set_distributed(0, 1)
    train = iter(data.train_dataloader())
    test = [b.float_images() for b in data.test_dataloader()]
    module, predict = pose_regressor(variant)
    params = [p for p in module.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=args.lr, weight_decay=0.05)

    def test_rotation_error() -> float:
        module.eval()
        with torch.no_grad():
            errors = [
                relative_pose_errors(predict(all_views(b)), dataset_cameras(b)[0])[0].flatten() for b in test
            ]
        module.train()
        return torch.cat(errors).mean().item()

    rows = [{"step": 0, "train_rot_deg": math.nan, "test_rot_deg": test_rotation_error(), "seconds": 0.0}]
    gt = [dataset_cameras(b)[0] for b in test]
    truth = (
        torch.cat([relative_pose_errors(torch.eye(4).expand_as(e), e)[0].flatten() for e in gt]).mean().item()
    )
    print(
        f"{variant}: {sum(p.numel() for p in params) / 1e6:.2f} M parameters; no rotation scores "
        f"{truth:.2f} deg on the test views; step 0 {rows[0]['test_rot_deg']:.2f} deg",
        flush=True,
    )
    seconds, window = 0.0, []
    for step in range(1, args.steps + 1):
        batch = next(train).float_images()
        start = time.perf_counter()
        extrinsics = predict(all_views(batch))
        gt_extrinsics, gt_intrinsics = dataset_cameras(batch)
        terms = camera_loss(extrinsics, gt_intrinsics, gt_extrinsics, gt_intrinsics)  # focal: not predicted
        loss = 10.0 * terms["rotation"] + terms["translation"]
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        seconds += time.perf_counter() - start
        window.append(math.degrees(terms["rotation"].item()))
        if step % args.every == 0 or step == args.steps:
            train_rot = sum(window) / len(window)
            row = {"step": step, "train_rot_deg": train_rot, "test_rot_deg": test_rotation_error(),
                   "seconds": seconds}  # fmt: skip
            rows.append(row)
            window = []
            print(
                f"{variant} step {step}: train {row['train_rot_deg']:.2f} deg, test {row['test_rot_deg']:.2f} "
                f"deg ({seconds:.0f} s)",
                flush=True,
            )
    for row in rows:
        row["no_rotation_deg"] = truth
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--data", type=Path, default=ROOT / "outputs" / "warmstart", help="shards under DATA/shards"
    )
    parser.add_argument("--scene-args", default="--seed 1 --scenes 96 --test-scenes 8",
                        help="synthetic.py options when making the shards")  # fmt: skip
    parser.add_argument("--size", type=int, default=42)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--every", type=int, default=250)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "pose-probe")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from learning_curves import ensure_shards

    shards = ensure_shards(args.data, args.size, args.scene_args)
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [
        f"Supervised pose probe: {args.steps} steps, batch {args.batch}, lr {args.lr}, data {shards}",
        "",
        "| variant | test rotation error, step 0 (deg) | last (deg) | no rotation (deg) "
        "| train, last window (deg) "
        "| seconds |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for variant in args.variants:
        rows = probe(variant, args, shards)
        with open(args.out / f"{variant}.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        first, last = rows[0], rows[-1]
        cells = [first["test_rot_deg"], last["test_rot_deg"], last["no_rotation_deg"], last["train_rot_deg"]]
        lines.append(f"| {variant} | " + " | ".join(f"{v:.2f}" for v in cells) + f" | {last['seconds']:.0f} |")
    (args.out / "PROBE.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
