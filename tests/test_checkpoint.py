"""aesplat.checkpoint: the one way every command reads a checkpoint. A file is data, never code: classes are
refused, hyper-parameters are checked against the typed settings, `last` falls back to the newest checkpoint
that loads, `best` is the best validation score, and the image size travels with the checkpoint."""

import os
import pickle
import re
from pathlib import Path

import pytest
import torch

from aesplat.checkpoint import (
    checked_hparams,
    checkpoint_sections,
    load_checkpoint,
    resolve_ckpt_path,
)
from aesplat.errors import UserError
from aesplat.model.weights import read_torch_file
from aesplat.types import DATA_RECORD
from tests.helpers import write_tiny_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict:
    """A tiny Lightning checkpoint (RUN/checkpoints/last.ckpt, RUN/config.yaml) and its loaded dict."""
    last = write_tiny_checkpoint(tmp_path_factory.mktemp("run"))
    return {"path": last, "ckpt": torch.load(last, weights_only=True)}


def crafted(tiny: dict, tmp_path: Path, **changes) -> Path:
    """The tiny checkpoint with its hyper-parameters changed (``section=value``; a dict merges)."""
    ckpt = torch.load(tiny["path"], weights_only=True)
    for section, value in changes.items():
        base = ckpt["hyper_parameters"].get(section)
        ckpt["hyper_parameters"][section] = {**base, **value} if isinstance(base, dict) else value
    path = tmp_path / "crafted.ckpt"
    torch.save(ckpt, path)
    return path


CLASS = {"class_path": "logging.FileHandler", "init_args": {"filename": "victim.txt", "mode": "w"}}


@pytest.mark.parametrize(
    "changes, where",
    [
        ({"net": {"options": {"x": CLASS}}}, "net.options.x.class_path"),
        ({"render": {"options": {"tile_size": CLASS}}}, "render.options.tile_size.class_path"),
        ({"loss": {"terms": [1, {"_class_path": "os.system"}]}}, "loss.terms[1]._class_path"),
        ({"_class_path": "os.system"}, "_class_path"),
        ({"_instantiator": "builtins.exec"}, "_instantiator"),
    ],
)
def test_hyper_parameters_that_name_a_class_are_refused(tiny, tmp_path, changes, where):
    ckpt = torch.load(crafted(tiny, tmp_path, **changes), weights_only=True)
    with pytest.raises(UserError, match=re.escape(f"name a class to instantiate ({where})")):
        checked_hparams(ckpt, "F", checkpoint_sections())


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"net": {"sh_degree": "2"}}, r"net.sh_degree is '2', not of type int"),
        ({"net": {"options": {"unknown": 1}}}, r"net.options.unknown is not a setting of this version"),
        ({"render": {"background": [0, 0]}}, r"render.background is \[0, 0\], not of type tuple"),
        ({"cameras": "oracle"}, r"cameras is 'oracle', not one of 'predicted', 'dataset'"),
    ],
)
def test_hyper_parameters_are_values_of_known_settings(tiny, tmp_path, changes, message):
    ckpt = torch.load(crafted(tiny, tmp_path, **changes), weights_only=True)
    with pytest.raises(UserError, match=message):
        checked_hparams(ckpt, "F", checkpoint_sections())


def test_the_written_hyper_parameters_pass(tiny):
    settings = checked_hparams(tiny["ckpt"], tiny["path"], checkpoint_sections())
    assert settings["net"]["sh_degree"] == 2 and settings["cameras"] == "predicted"


def test_a_pickled_function_is_reported_as_refused_not_as_damaged(tmp_path):
    """torch names a blocked module's function "GLOBAL" in capitals: still a refusal, never "truncated"."""
    path = tmp_path / "payload.ckpt"
    torch.save({"state_dict": {}, "hook": os.system}, path)
    with pytest.raises(UserError, match="holds Python objects besides tensors; it is not loaded"):
        read_torch_file(path, "checkpoint")
    pickle_path = tmp_path / "class.pt"
    torch.save({"x": pickle.PickleError()}, pickle_path)
    with pytest.raises(UserError, match="holds Python objects besides tensors"):
        read_torch_file(pickle_path, "checkpoint")


def test_an_unreadable_file_says_so(tiny, monkeypatch):
    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(torch, "load", denied)
    with pytest.raises(UserError, match=r"cannot be read: Permission denied"):
        read_torch_file(tiny["path"], "checkpoint")


def run_with(tmp_path: Path, tiny: dict, files: dict[str, int | str]) -> Path:
    """A run folder holding checkpoints: name -> global step (or "truncated")."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for offset, (name, step) in enumerate(files.items()):
        path = run / name
        if step == "truncated":
            path.write_bytes(tiny["path"].read_bytes()[:1000])
        else:
            torch.save({**tiny["ckpt"], "global_step": step}, path)
        os.utime(path, (1e9 + offset, 1e9 + offset))  # written in this order
    return run


def test_last_falls_back_to_the_newest_checkpoint_that_loads(tiny, tmp_path):
    run = run_with(tmp_path, tiny, {"checkpoints/best-step2.ckpt": 2, "hpc_ckpt_1.ckpt": 4,
                                    "checkpoints/last.ckpt": "truncated"})  # fmt: skip
    path, skipped = resolve_ckpt_path("last", run)
    assert path == run / "hpc_ckpt_1.ckpt"
    assert len(skipped) == 1 and "last.ckpt is truncated or corrupt" in skipped[0]


def test_last_prefers_the_highest_step_not_the_newest_file(tiny, tmp_path):
    run = run_with(tmp_path, tiny, {"checkpoints/last.ckpt": 6, "checkpoints/best-step4.ckpt": 4})
    assert resolve_ckpt_path("last", run) == (run / "checkpoints" / "last.ckpt", [])


def test_last_of_a_run_without_checkpoints(tmp_path):
    assert resolve_ckpt_path("last", tmp_path, fresh_if_none=True) == (None, [])
    with pytest.raises(UserError, match="holds no checkpoint"):
        resolve_ckpt_path("last", tmp_path)


def test_best_is_the_best_validation_score(tiny, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    key = "RunCheckpoint{'monitor': 'val/psnr'}"
    scores = {"best-step2.ckpt": 11.0, "best-step4.ckpt": 14.5, "best-step6.ckpt": 12.0}
    for name, score in scores.items():  # each file saved with its own score among the best ones
        best = {str(run / "checkpoints" / name): torch.tensor(score)}
        callbacks = {key: {"monitor": "val/psnr", "best_k_models": best}}
        torch.save({**tiny["ckpt"], "callbacks": callbacks}, run / "checkpoints" / name)
    last = {key: {"monitor": "val/psnr", "best_k_models": {"elsewhere/best-step0.ckpt": torch.tensor(99.0)}}}
    torch.save({**tiny["ckpt"], "callbacks": last}, run / "checkpoints" / "last.ckpt")
    assert resolve_ckpt_path("best", run)[0] == run / "checkpoints" / "best-step4.ckpt"
    assert resolve_ckpt_path("best", run, mode="min")[0] == run / "checkpoints" / "best-step2.ckpt"
    with pytest.raises(UserError, match="no checkpoint .* was saved for its val/lpips"):
        resolve_ckpt_path("best", run, monitor="val/lpips")


def test_the_image_size_travels_with_the_checkpoint(tiny, tmp_path):
    """Out of its run folder (no config.yaml beside it), the size comes from the checkpoint's own record; a
    checkpoint without either says nothing, rather than a guess."""
    record = tmp_path / "recorded.ckpt"
    torch.save({**tiny["ckpt"], DATA_RECORD: {"image_size": 42}}, record)
    assert load_checkpoint(record).image_size == 42
    bare = tmp_path / "bare.ckpt"
    torch.save(tiny["ckpt"], bare)
    assert load_checkpoint(bare).trained_size is None
    with pytest.raises(UserError, match="bare.ckpt does not say which image size it was trained at"):
        _ = load_checkpoint(bare).image_size
    assert load_checkpoint(tiny["path"]).image_size == 28  # the run's config.yaml


def test_options_of_older_checkpoints_load_typed(tiny, tmp_path):
    """Checkpoints store only the options that were set: they load into the typed sections."""
    path = crafted(tiny, tmp_path, render={"options": {"tile_size": 16}})
    loaded = load_checkpoint(path)
    assert loaded.render["options"]["tile_size"] == 16 and loaded.render["options"]["chunk"] == 32
    assert loaded.render_options()["tile_size"] == 16 and "backend" not in loaded.render_options()
