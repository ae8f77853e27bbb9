"""`aesplat test --ckpt_path` on one of NAS3R's checkpoints: the network is set from the file, its tensors load
strictly into the module, and the pose figures come out. The network is the parity fixture's (NAS3R's own
classes at a reduced size), registered as a model size; NAS3R's released files are `large`."""

from __future__ import annotations

import json

import pytest
import torch

from aesplat.lightning_cli import run_lightning
from aesplat.model import model as model_module
from aesplat.model.nas3r import nas3r_net
from aesplat.train import AESplatModule
from tests.model.nas3r_files import FIXTURE, SIZE, fixture_config, write_nas3r_ckpt


@pytest.mark.parametrize("network", ["nas3r", "nas3r-I"])
def test_test_command_evaluates_a_nas3r_checkpoint(smoke_shards, tmp_path, monkeypatch, network):
    fixture = torch.load(FIXTURE, weights_only=True)
    monkeypatch.setitem(model_module.SIZES, SIZE, fixture_config(fixture))
    monkeypatch.setattr("aesplat.lightning_cli.nas3r_net", lambda variant: {**nas3r_net(variant), "size": SIZE})
    seen = {}

    def record(module):  # the network as the test loop starts, after Lightning's strict load of the checkpoint
        seen["camera_token"] = module.model.aggregator.camera_token.detach().clone()

    monkeypatch.setattr(AESplatModule, "on_test_start", record, raising=False)
    ckpt = write_nas3r_ckpt(tmp_path / f"{network}.ckpt", fixture["states"][network])
    run = tmp_path / "run"
    run_lightning(["test", "-c", "conf/smoke.yaml", "--data.root", str(smoke_shards), "--trainer.logger",
                   "false", "--trainer.default_root_dir", str(run), "--ckpt_path", str(ckpt)])  # fmt: skip
    summary = json.loads((run / "test-latest" / "summary.json").read_text())
    assert summary["cameras"] == "predicted" and summary["num_scenes"] == 2
    assert summary["pose"]["all"]["last"]["median"]["rot"] is not None
    assert summary["metrics"]["psnr"] is not None
    assert torch.equal(
        seen["camera_token"], fixture["states"][network]["backbone.model.aggregator.camera_token"]
    )
