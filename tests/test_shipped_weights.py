"""weights/demo-warmstart.pt, the warm start `make demo` starts from (made by `make warmstart`)."""

from pathlib import Path

import torch
from omegaconf import OmegaConf

from aesplat.model import NetConfig

ROOT = Path(__file__).resolve().parents[1]


def test_the_shipped_warm_start_loads_completely_into_the_demo_model(monkeypatch):
    monkeypatch.chdir(ROOT)  # the config names the file relative to the repository
    net = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "demo.yaml").model.net)
    path = ROOT / net["weights"]
    assert path.stat().st_size < 50 * 2**20
    model = NetConfig(**net).build()
    report = model.weights_report
    assert report.format == "aesplat" and not report.missing and not report.unexpected
    assert set(report.loaded) == set(model.state_dict())
    raw = torch.load(path, weights_only=True)
    assert "make warmstart" in raw["note"]
    assert (
        raw["hyper_parameters"]["cameras"] == "dataset" and raw["hyper_parameters"]["loss"]["pose_weight"] > 0
    )
    # made with the demo's own scale parametrisation and rasterization mode (not in the tensors)
    made = raw["hyper_parameters"]
    demo = OmegaConf.load(ROOT / "conf" / "demo.yaml").model
    assert made["net"]["options"]["scale_mode"] == net["options"]["scale_mode"]
    assert made["render"]["options"]["rasterize_mode"] == demo.render.options.rasterize_mode
    for key, value in model.state_dict().items():  # the tensors themselves, not just their names
        torch.testing.assert_close(value, raw["state_dict"][f"model.{key}"], rtol=0, atol=0)
