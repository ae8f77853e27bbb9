"""The paper's appearance head (``concat``) is unchanged: a network saved before the view aggregation became
selectable loads into today's code and gives the same outputs (fixture written by
``fixtures/make_concat_fixture.py`` at commit c5c0f51, square 14-pixel images)."""

from dataclasses import fields
from pathlib import Path

import pytest
import torch

from aesplat.model import (
    AESplatModel,
    ConcatAppearance,
    EncoderConfig,
    ModelConfig,
    NetConfig,
    TransformerConfig,
)

FIXTURE = Path(__file__).parent / "fixtures" / "concat_v1.pt"


@pytest.fixture(scope="module")
def saved() -> dict:
    return torch.load(FIXTURE, weights_only=True)


def _config(saved: dict) -> ModelConfig:
    cfg = dict(saved["config"])
    cfg["encoder"] = EncoderConfig(**cfg["encoder"])
    cfg["transformer"] = TransformerConfig(**cfg["transformer"])
    known = {f.name for f in fields(ModelConfig)}
    assert set(cfg) <= known, f"fields the old config had and today's lacks: {set(cfg) - known}"
    return ModelConfig(**cfg)


def test_an_old_concat_checkpoint_gives_the_same_outputs(saved):
    model = AESplatModel(_config(saved)).eval()
    state = {k.removeprefix("model."): v for k, v in saved["state_dict"].items()}
    model.load_state_dict(state, strict=True)  # same parameter names and shapes, none missing or extra
    with torch.no_grad():
        out = model(saved["inputs"]["context"], saved["inputs"]["target"])
    got = {name: getattr(out.gaussians, name) for name in ("means", "quats", "scales", "opacities", "sh")}
    got.update(extrinsics=out.extrinsics, intrinsics=out.intrinsics, depth=out.depth)
    assert set(got) == set(saved["expected"])
    for name, expected in saved["expected"].items():
        torch.testing.assert_close(got[name], expected, rtol=1e-5, atol=1e-6, msg=name)
    # the higher-order SH (the appearance head's output) are not trivially zero
    assert saved["expected"]["sh"][..., 1:, :].abs().max() > 1e-3


def test_an_old_run_configuration_builds_the_same_appearance_head(saved):
    """A run's saved ``model.net`` section from before (no ``view_aggregation``) builds the paper's head, with
    the same appearance parameters."""
    net = saved["hyper_parameters"]["net"]
    assert "view_aggregation" not in net
    assert NetConfig(**net).view_aggregation == "concat"
    model = NetConfig(**net).build()
    assert isinstance(model.appearance, ConcatAppearance)
    old = {k.removeprefix("model.") for k in saved["state_dict"] if k.startswith("model.appearance.")}
    assert old == {k for k in model.state_dict() if k.startswith("appearance.")}
