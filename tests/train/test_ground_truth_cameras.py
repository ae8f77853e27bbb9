"""scripts/ground_truth_cameras.py: the diagnostic that swaps the camera head's poses for the ground truth."""

import subprocess
import sys

import torch

from aesplat.geometry import relative_to_first
from aesplat.train.metrics import relative_pose_errors

from ..script_loader import SCRIPTS, load_script
from .test_module import make_data, smoke_config

SCRIPT = SCRIPTS / "ground_truth_cameras.py"


def test_renders_and_gaussians_use_the_ground_truth_poses(smoke_shards):
    script = load_script("ground_truth_cameras")
    module = script.GroundTruthCamerasModule(**smoke_config()["model"])
    batch = next(iter(make_data(smoke_shards).train_dataloader())).float_images()
    out, rendered = module(batch)
    gt = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1)
    torch.testing.assert_close(out.extrinsics, relative_to_first(gt), atol=1e-5, rtol=0)
    rot, trans = relative_pose_errors(out.extrinsics, gt)
    assert float(rot.max()) < 1e-2 and float(trans.max()) < 1e-2
    assert torch.isfinite(rendered.color).all()
    # the poses are cleared after each forward pass, so a stale pose can never leak into the next batch
    assert module.model.camera_head.poses is None
    # gradients still reach the depth head through the ground-truth cameras
    rendered.color.mean().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.model.depth_head.parameters())


def test_the_script_takes_the_lightning_cli_arguments():
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "fit", "-c", "conf/smoke.yaml", "--print_config"],
        capture_output=True, text=True, cwd=SCRIPT.parents[1], timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "net:" in done.stdout and "trainer:" in done.stdout
