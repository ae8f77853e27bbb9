"""scripts/pose_sensitivity.py: the yaw landscape at the data set's cameras, the downhill test at own poses."""

import json

import torch

from aesplat.geometry import quat_to_matrix
from tests.helpers import write_tiny_checkpoint
from tests.script_loader import load_script
from tests.train.helpers import make_data, smoke_config


def test_yaw_helpers_round_trip():
    script = load_script("pose_sensitivity")
    pose = torch.eye(4)
    pose[:3, :3] = quat_to_matrix(torch.nn.functional.normalize(torch.tensor([0.9, 0.2, -0.3, 0.1]), dim=0))
    pose[:3, 3] = torch.tensor([0.5, -1.0, 2.0])
    turned = script.turn_yaw(pose, 7.0)
    torch.testing.assert_close(turned[:3, 3], pose[:3, 3])  # the camera turns on the spot
    assert abs(script.relative_yaw(pose, turned) - 7.0) < 1e-4
    assert abs(script.relative_yaw(turned, pose) + 7.0) < 1e-4
    # a turn about the camera's own y axis keeps that axis
    torch.testing.assert_close(turned[:3, 1], pose[:3, 1])


def test_measures_a_posed_checkpoint(smoke_shards, tmp_path):
    script = load_script("pose_sensitivity")
    # A checkpoint as `aesplat fit --model.cameras dataset` writes it.
    ckpt = write_tiny_checkpoint(tmp_path / "run", cameras="dataset")
    module = script.load_module(ckpt)
    assert module.cameras == "dataset" and not module.training

    size = smoke_config()["data"]["image_size"]
    out = tmp_path / "sensitivity.json"
    result = script.main(["--ckpt", str(ckpt), "--data-root", str(smoke_shards), "--image-size", str(size),
                          "--scenes", "2", "--offsets", "-3", "0", "3", "--out", str(out)])  # fmt: skip
    assert json.loads(out.read_text())["landscape_psnr"] == result["landscape_psnr"]

    # Offset 0 is exactly the render of the posed module itself.
    psnrs = []
    with torch.no_grad():
        for _, batch in zip(range(2), make_data(smoke_shards, num_workers=0).test_dataloader()):
            batch = module.on_after_batch_transfer(batch, 0)
            _, rendered = module(batch)
            mse = ((rendered.color - batch.target.images) ** 2).mean(dim=(2, 3, 4))[0]
            psnrs += (-10 * torch.log10(mse)).tolist()
    assert result["views"] == len(psnrs)
    assert abs(result["landscape_psnr"][1] - sum(psnrs) / len(psnrs)) < 1e-3
    # Turned cameras render something else, and each downhill verdict follows its two losses.
    assert min(abs(result["landscape_psnr"][i] - result["landscape_psnr"][1]) for i in (0, 2)) > 0.05
    for row in result["downhill"]:
        assert row["agrees"] == ((row["loss_plus"] < row["loss_minus"]) == (row["yaw_error_deg"] > 0))
