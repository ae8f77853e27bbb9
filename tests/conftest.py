import os
import signal

import pytest
import torch

from tests.helpers import make_shards

os.environ.setdefault("WANDB_MODE", "disabled")
torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture(scope="session")
def shards(tmp_path_factory):
    """Shards of two training scenes and one test scene, 28 px, for the command-line tests."""
    return make_shards(tmp_path_factory.mktemp("errors_data"), scenes=2, test_scenes=1, seed=1)


@pytest.fixture
def pretend_gsplat(monkeypatch):
    """Pretend this is a CUDA machine with gsplat installed (a GPU node), without touching a GPU."""
    from aesplat.render import interface

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(interface, "gsplat_available", lambda: True)


@pytest.fixture
def stop_signals_heeded():
    """A test that sends itself SIGHUP or SIGINT needs them at their defaults: the suite may run under
    ``nohup`` or as a background job, which start it with those ignored (and the commands leave an ignored
    signal ignored)."""
    defaults = {signal.SIGHUP: signal.SIG_DFL, signal.SIGINT: signal.default_int_handler}
    saved = {s: signal.signal(s, handler) for s, handler in defaults.items()}
    yield
    for s, handler in saved.items():
        signal.signal(s, handler)
