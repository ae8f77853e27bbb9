import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "disabled")
torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture
def pretend_gsplat(monkeypatch):
    """Pretend this is a CUDA machine with gsplat installed (a GPU node), without touching a GPU."""
    from aesplat.render import interface

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(interface, "gsplat_available", lambda: True)
