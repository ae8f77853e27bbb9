"""NAS3R's checkpoints for the tests: the parity fixture's network (NAS3R's own classes at a reduced size,
written by benchmarks/nas3r_parity.py) as a model size, and files laid out as NAS3R's released ones."""

from __future__ import annotations

from pathlib import Path

import torch

from aesplat.model.encoder import EncoderConfig
from aesplat.model.model import ModelConfig
from aesplat.model.transformer import TransformerConfig

FIXTURE = Path(__file__).parent / "fixtures" / "nas3r_parity.pt"
SIZE = "nas3r-fixture"  # the name the tests register the fixture's network under (monkeypatch SIZES)


def fixture_config(fixture: dict) -> ModelConfig:
    """The fixture's network as this project's settings."""
    net = dict(fixture["net"])
    transformer = dict(net.pop("transformer"))
    transformer["layers"] = tuple(transformer["layers"])
    encoder = net.pop("encoder")
    net = {k: tuple(v) if isinstance(v, list) else v for k, v in net.items()}
    return ModelConfig(**net, encoder=EncoderConfig(**encoder), transformer=TransformerConfig(**transformer))


def write_nas3r_ckpt(path: Path, state: dict) -> Path:
    """A file laid out as NAS3R's released checkpoints: a Lightning checkpoint, the network under `encoder.`."""
    weights = {"encoder." + k: v for k, v in state.items()}
    payload = {"state_dict": weights, "pytorch-lightning_version": "2.4.0", "epoch": 3, "global_step": 400000,
               "loops": {}, "callbacks": {}, "optimizer_states": [], "lr_schedulers": []}  # fmt: skip
    torch.save(payload, path)
    return path
