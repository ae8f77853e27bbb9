"""NAS3R's checkpoints in the commands: recognised from their keys, refused in one line when they cannot load,
and run by `aesplat predict` as this project's network. The network is the parity fixture's (NAS3R's own
classes at a reduced size, tests/model/fixtures/nas3r_parity.pt), registered as a model size for the test;
NAS3R's released files are `large`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.errors import UserError
from aesplat.model import model as model_module
from aesplat.model.model import build_model
from aesplat.model.nas3r import (
    convert_nas3r_state,
    is_nas3r_state,
    load_nas3r_state,
    nas3r_net,
    nas3r_variant,
)
from tests.helpers import aesplat as aesplat_exit
from tests.model.nas3r_files import FIXTURE, SIZE, fixture_config, write_nas3r_ckpt


def aesplat(capsys, *args: str) -> tuple[int, str]:
    """`aesplat ARGS` in this process: (exit status, stderr); a command that returns normally exits 0."""

    try:
        return aesplat_exit(capsys, *args)
    except pytest.fail.Exception:  # it did not raise SystemExit: it finished
        return 0, capsys.readouterr().err


@pytest.fixture(scope="module")
def fixture() -> dict:
    return torch.load(FIXTURE, map_location="cpu", weights_only=True)


@pytest.fixture
def small_nas3r(fixture, monkeypatch):
    """NAS3R files of the fixture's network load as the size SIZE (the released ones are `large`)."""
    monkeypatch.setitem(model_module.SIZES, SIZE, fixture_config(fixture))

    def small_net(variant):
        return {**nas3r_net(variant), "size": SIZE}

    monkeypatch.setattr("aesplat.checkpoint.nas3r_net", small_net)


def write_photos(tmp_path: Path, images: torch.Tensor) -> list[Path]:
    paths = []
    for i, image in enumerate(images):
        path = tmp_path / f"view{i}.png"
        Image.fromarray((image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(path)
        paths.append(path)
    return paths


def test_the_variant_is_read_from_the_keys(fixture):
    plain = {"encoder." + k: v for k, v in fixture["states"]["nas3r"].items()}
    with_k = {"encoder." + k: v for k, v in fixture["states"]["nas3r-I"].items()}
    assert is_nas3r_state(plain) and is_nas3r_state(with_k)
    assert not is_nas3r_state({"model.camera_head.x": torch.zeros(1)})
    assert nas3r_variant(plain, "f").intrinsics is False and nas3r_variant(with_k, "f").intrinsics is True
    assert nas3r_variant(plain, "f").sh_degree == 4  # 83 Gaussian channels
    net = nas3r_net(nas3r_variant(with_k, "f"))
    assert net["size"] == "large" and net["appearance"] == "baseline" and net["options"]["intrinsics_tokens"]
    # NAS3R's camera head and pixel corners: the file runs as in NAS3R's own evaluation
    assert net["options"]["camera_mask"] is False and net["options"]["pixel_offset"] == 0.0
    extra = {"encoder.backbone.model.point_head.norm.weight": torch.ones(2), "step_tracker": torch.zeros(1)}
    converted, ignored = convert_nas3r_state({**plain, **extra})
    assert "aggregator.camera_token" in converted and "gaussian_head.input_merger.0.weight" in converted
    assert sorted(ignored) == ["encoder.backbone.model.point_head.norm.weight", "step_tracker"]


def test_a_nas3r_m_or_incomplete_checkpoint_is_one_line():
    croco = {"encoder.backbone.enc_blocks.0.attn.qkv.weight": torch.zeros(3, 1),
             "encoder.gaussian_param_head.scratch.output_conv2.2.weight": torch.zeros(83, 1, 1, 1)}  # fmt: skip
    with pytest.raises(UserError, match="NAS3R-M checkpoint") as err:
        nas3r_variant(croco, "m.ckpt")
    assert "\n" not in str(err.value)
    trunk_only = {"encoder.backbone.model.aggregator.camera_token": torch.zeros(1, 2, 1, 8)}
    with pytest.raises(UserError, match="without its Gaussian head"):
        nas3r_variant(trunk_only, "t.ckpt")


def test_a_network_without_intrinsics_tokens_refuses_an_i_checkpoint(fixture):
    cfg = fixture_config(fixture)
    model = model_module.AESplatModel(cfg)
    with_k = {"encoder." + k: v for k, v in fixture["states"]["nas3r-I"].items()}
    with pytest.raises(UserError, match="intrinsics_tokens: true"):
        load_nas3r_state(model, with_k, "i.ckpt")


def test_a_nas3r_checkpoint_of_another_size_is_one_line(fixture):
    plain = {"encoder." + k: v for k, v in fixture["states"]["nas3r"].items()}
    with pytest.raises(UserError, match="loads into the `large` network") as err:
        load_nas3r_state(build_model("tiny", "baseline", 4), plain, "small.ckpt")
    assert "\n" not in str(err.value)


def test_predict_runs_a_nas3r_checkpoint_as_its_forward(fixture, small_nas3r, tmp_path, capsys):
    """`aesplat predict --ckpt NAS3R.ckpt`: the cameras it writes are the network's on the photos it read."""
    from aesplat.checkpoint import load_checkpoint
    from aesplat.images import load_image

    ckpt = write_nas3r_ckpt(tmp_path / "re10k_nas3r.ckpt", fixture["states"]["nas3r"])
    entry = next(c for c in fixture["cases"] if c["case"] == "2+1")["fixture"]
    photos = write_photos(tmp_path, entry["inputs"]["images"][0, :2])
    out = tmp_path / "pred"
    code, err = aesplat(capsys, "predict", "--ckpt", str(ckpt), *map(str, photos), "--out", str(out),
                        "--size", "28", "--novel-frames", "2", "--no-progress")  # fmt: skip
    assert code == 0, err
    views = json.loads((out / "cameras.json").read_text())["views"]
    loaded = load_checkpoint(ckpt)
    assert loaded.trained_size == 224 and loaded.net["appearance"] == "baseline"
    token = fixture["states"]["nas3r"]["backbone.model.aggregator.camera_token"]
    assert torch.equal(loaded.model.aggregator.camera_token, token)  # NAS3R's tensors, not an initialisation
    images = torch.stack([load_image(p, 28, (0.0, 0.0, 0.0), patch=14).image for p in photos])[None]
    with torch.no_grad():
        direct = loaded.model(images)
    written = torch.tensor([v["camera_to_world"] for v in views])
    torch.testing.assert_close(written, direct.extrinsics[0], rtol=0, atol=1e-5)
    assert (out / "gaussians.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_an_i_checkpoint_needs_intrinsics_and_the_others_refuse_them(fixture, small_nas3r, tmp_path, capsys):
    entry = next(c for c in fixture["cases"] if c["case"] == "2+1-I")["fixture"]
    photos = [str(p) for p in write_photos(tmp_path, entry["inputs"]["images"][0, :2])]
    with_k = write_nas3r_ckpt(tmp_path / "re10k_nas3r_pretrained-I.ckpt", fixture["states"]["nas3r-I"])
    plain = write_nas3r_ckpt(tmp_path / "re10k_nas3r.ckpt", fixture["states"]["nas3r"])
    common = ["--size", "28", "--novel-frames", "2", "--no-progress"]
    code, err = aesplat(
        capsys, "predict", "--ckpt", str(with_k), *photos, "--out", str(tmp_path / "a"), *common
    )
    assert code == 1 and "give --intrinsics FX,FY,CX,CY" in err and len(err.strip().splitlines()) == 1
    code, err = aesplat(capsys, "predict", "--ckpt", str(plain), *photos, "--out", str(tmp_path / "b"),
                        "--intrinsics", "0.9,0.9,0.5,0.5", *common)  # fmt: skip
    assert code == 1 and "leave --intrinsics out" in err
    code, err = aesplat(capsys, "predict", "--ckpt", str(with_k), *photos, "--out", str(tmp_path / "c"),
                        "--intrinsics", "0.9,0.9,2,0.5", *common)  # fmt: skip
    assert code == 1 and "principal point inside the photo" in err
    code, err = aesplat(capsys, "predict", "--ckpt", str(with_k), *photos, "--out", str(tmp_path / "d"),
                        "--intrinsics", "0.9,0.9,0.5,0.5", *common)  # fmt: skip
    assert code == 0, err
    views = json.loads((tmp_path / "d" / "cameras.json").read_text())["views"]
    # -I takes the intrinsics it is given (a 28 x 42 photo: fx, fy, cx, cy as normalised by its own sides)
    torch.testing.assert_close(torch.tensor(views[1]["intrinsics_normalized"]),
                               torch.tensor([[0.9, 0.0, 0.5], [0.0, 0.9, 0.5], [0.0, 0.0, 1.0]]))  # fmt: skip


def test_a_truncated_nas3r_checkpoint_is_one_line(fixture, tmp_path, capsys):
    ckpt = write_nas3r_ckpt(tmp_path / "re10k_nas3r.ckpt", fixture["states"]["nas3r"])
    data = ckpt.read_bytes()
    ckpt.write_bytes(data[: len(data) // 2])
    code, err = aesplat(capsys, "predict", "--ckpt", str(ckpt), "a.png", "b.png", "--out", str(tmp_path / "p"))
    assert code == 1 and "truncated or corrupt" in err and len(err.strip().splitlines()) == 1


def test_fit_does_not_resume_a_nas3r_checkpoint(fixture, tmp_path, capsys):
    ckpt = write_nas3r_ckpt(tmp_path / "re10k_nas3r.ckpt", fixture["states"]["nas3r"])
    code, err = aesplat(capsys, "fit", "-c", "conf/smoke.yaml", "--trainer.default_root_dir",
                        str(tmp_path / "run"), "--ckpt_path", str(ckpt))  # fmt: skip
    assert code == 1 and f"start from NAS3R's weights with --model.net.weights {ckpt}" in err


def test_a_nas3r_checkpoint_loads_as_weights_with_a_new_appearance_head(fixture, small_nas3r, tmp_path):
    ckpt = write_nas3r_ckpt(tmp_path / "re10k_nas3r.ckpt", fixture["states"]["nas3r"])
    with pytest.warns(UserWarning, match="appearance head .* starts afresh"):
        model = build_model(SIZE, "full", 4, view_aggregation="pool", near=1.0, far=100.0, weights=str(ckpt))
    report = model.weights_report
    assert report.format == "nas3r" and not report.missing and not report.unexpected
    assert model.pretrained_backbone
    state = fixture["states"]["nas3r"]
    assert torch.equal(model.aggregator.camera_token, state["backbone.model.aggregator.camera_token"])
    assert torch.equal(
        model.gaussian_head.input_merger[0].weight, state["gaussian_param_head.input_merger.0.weight"]
    )
