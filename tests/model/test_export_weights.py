"""scripts/export_weights.py / aesplat.model.weights.export_weights: a fit checkpoint's model, alone."""

import pytest
import torch

from aesplat.model import build_model
from aesplat.model.weights import export_weights

from ..script_loader import load_script


def _fake_fit_checkpoint(path, model):
    state = {f"model.{k}": v for k, v in model.state_dict().items()}
    state["val_psnr.total"] = torch.tensor(3.0)  # a metric's state: not the model's
    torch.save({"state_dict": state, "optimizer_states": [{"state": {0: {"exp_avg": torch.ones(1000)}}}],
                "hyper_parameters": {"net": {"size": "tiny", "options": {"camera_correlation": True}}},
                "global_step": 7}, path)  # fmt: skip


def test_exported_weights_load_into_the_same_model_and_nothing_else_is_kept(tmp_path, capsys):
    torch.manual_seed(0)
    trained = build_model("tiny", sh_degree=2, camera_correlation=True)
    ckpt, out = tmp_path / "last.ckpt", tmp_path / "w" / "weights.pt"
    _fake_fit_checkpoint(ckpt, trained)
    load_script("export_weights").main(["--ckpt", str(ckpt), "--out", str(out), "--note", "made by a test"])
    assert "MiB" in capsys.readouterr().out
    raw = torch.load(out, weights_only=True)
    assert raw["note"] == "made by a test" and raw["global_step"] == 7 and "optimizer_states" not in raw
    assert set(raw["state_dict"]) == {f"model.{k}" for k in trained.state_dict()}
    torch.manual_seed(1)
    loaded = build_model("tiny", sh_degree=2, camera_correlation=True, weights=str(out))
    for key, value in trained.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value, rtol=0, atol=0)
    with pytest.raises(ValueError, match="camera_correlation"):  # another network: the error names the file's
        build_model("tiny", sh_degree=4, camera_correlation=True, weights=str(out))


def test_only_fit_checkpoints_are_exported(tmp_path):
    path = tmp_path / "encoder.pt"
    torch.save({"blocks.0.norm1.weight": torch.ones(3)}, path)
    with pytest.raises(ValueError, match="not an `aesplat fit` checkpoint"):
        export_weights(path, tmp_path / "out.pt")


def test_a_failed_export_keeps_the_earlier_file_and_leaves_no_partial_file(tmp_path, monkeypatch):
    import errno

    ckpt, out = tmp_path / "last.ckpt", tmp_path / "weights.pt"
    _fake_fit_checkpoint(ckpt, build_model("tiny", sh_degree=2, camera_correlation=True))
    out.write_bytes(b"the earlier weights")
    real_save = torch.save

    def full_disk(obj, f):
        real_save({"half": torch.ones(10)}, f)  # some bytes reach the disk, then it is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(OSError, match="No space left") as err:
        export_weights(ckpt, out)
    assert err.value.filename == str(out)
    assert out.read_bytes() == b"the earlier weights" and sorted(p.name for p in tmp_path.iterdir()) == [
        "last.ckpt", "weights.pt",
    ]  # fmt: skip
