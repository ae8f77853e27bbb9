"""A run's checkpoints on any file system: written whole or not at all, a final save at the end of every fit,
and a moved run folder resuming into its own last.ckpt."""

import errno
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from aesplat.files import PARTIAL_SUFFIX, atomic_write
from aesplat.train.callbacks import RunCheckpoint
from aesplat.train.checkpoint_io import AtomicCheckpointIO
from tests.helpers import REPO
from tests.train.helpers import make_data, make_module, make_trainer


def state(step: int) -> dict:
    return {"global_step": step, "state_dict": {"w": torch.full((256, 256), float(step))}}


def test_a_full_disk_during_a_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    io, path = AtomicCheckpointIO(), tmp_path / "checkpoints" / "last.ckpt"
    io.save_checkpoint(state(1), path)
    real_save = torch.save

    def fills_the_disk(obj, f, *args, **kwargs):  # half a checkpoint, then ENOSPC (as a full disk does)
        real_save(obj, f, *args, **kwargs)
        f.truncate(f.tell() // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", fills_the_disk)
    with pytest.raises(OSError, match="No space left") as info:
        io.save_checkpoint(state(2), path)
    assert info.value.filename == str(path)  # named, so the one-line report says which file
    assert io.load_checkpoint(path)["global_step"] == 1
    assert [p.name for p in path.parent.iterdir()] == ["last.ckpt"]  # no temporary file left behind


def test_a_save_never_writes_into_the_previous_file_nor_renames_across_file_systems(tmp_path, monkeypatch):
    """The cluster layout: $TMPDIR on a local disk, the run folder elsewhere. A rename between two folders
    fails there (EXDEV), and the fallback copy would truncate the previous last.ckpt before writing it; the save
    must only ever create a new file in the checkpoint's folder and rename it within that folder."""
    elsewhere = tmp_path / "local-tmp"
    elsewhere.mkdir()
    monkeypatch.setenv("TMPDIR", str(elsewhere))
    path = tmp_path / "run" / "checkpoints" / "last.ckpt"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"previous")
    real_replace, real_rename, real_open = os.replace, os.rename, open

    def same_device_only(real):
        def move(src, dst, *args, **kwargs):
            if Path(src).resolve().parent != Path(dst).resolve().parent:
                raise OSError(errno.EXDEV, "Invalid cross-device link", str(src))
            return real(src, dst, *args, **kwargs)

        return move

    def never_into_the_previous(file, mode="r", *args, **kwargs):
        if Path(str(file)).resolve() == path.resolve() and any(m in mode for m in "wa+"):
            raise AssertionError(f"{path} opened for writing ({mode})")
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "replace", same_device_only(real_replace))
    monkeypatch.setattr(os, "rename", same_device_only(real_rename))
    monkeypatch.setattr("builtins.open", never_into_the_previous)
    AtomicCheckpointIO().save_checkpoint(state(3), path)
    assert torch.load(path, weights_only=True)["global_step"] == 3


def test_atomic_write_removes_its_temporary_file_when_interrupted(tmp_path):
    target = tmp_path / "file.bin"
    target.write_bytes(b"old")

    def interrupted(f):
        f.write(b"new, half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, interrupted)
    assert target.read_bytes() == b"old" and list(tmp_path.iterdir()) == [target]


SAVER = textwrap.dedent(
    """
    import sys, tempfile, torch
    from aesplat.files import atomic_write  # AtomicCheckpointIO.save_checkpoint, without importing Lightning
    path, tempfile.tempdir = sys.argv[1], sys.argv[2]  # $TMPDIR on another file system, as on a cluster
    weights = torch.arange(8 << 20, dtype=torch.float32)  # 32 MB: a save takes long enough to be killed in it
    print("ready", flush=True)
    step = 0
    while True:
        step += 1
        state = {"global_step": step, "state_dict": {"w": weights + step}}
        atomic_write(path, lambda f: torch.save(state, f))
    """
)


def test_kill_9_during_saves_leaves_a_whole_checkpoint(tmp_path):
    """A process saving over last.ckpt again and again, killed with SIGKILL at random moments: every time, the
    file that is left loads and holds a whole checkpoint."""
    path = tmp_path / "run" / "last.ckpt"
    tmpdir = "/dev/shm" if Path("/dev/shm").is_dir() else str(tmp_path)
    rng = random.Random(0)
    for _ in range(3):
        saver = subprocess.Popen([sys.executable, "-c", SAVER, str(path), tmpdir], stdout=subprocess.PIPE,
                                 cwd=REPO)  # fmt: skip
        assert saver.stdout.readline().strip() == b"ready"
        deadline = time.monotonic() + 60
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(rng.uniform(0.05, 0.5))
        os.kill(saver.pid, signal.SIGKILL)
        saver.wait()
        ckpt = torch.load(path, weights_only=True)
        expected = torch.arange(8 << 20, dtype=torch.float32) + ckpt["global_step"]
        assert ckpt["global_step"] >= 1 and torch.equal(ckpt["state_dict"]["w"], expected)
        for partial in path.parent.glob(f".*{PARTIAL_SUFFIX}"):
            partial.unlink()  # what a killed save leaves; the next fit removes it (remove_partials)


def fit(smoke_shards, run: Path, max_steps: int, every: int, ckpt_path=None) -> L.Trainer:
    L.seed_everything(0)
    last = RunCheckpoint(dirpath=run / "checkpoints", save_last=True, save_top_k=0, every_n_train_steps=every)
    trainer = make_trainer(max_steps, run, callbacks=[last], plugins=[AtomicCheckpointIO()])
    trainer.fit(make_module(), make_data(smoke_shards, train_batches_per_epoch=4), ckpt_path=ckpt_path)
    return trainer


def step_of(path: Path) -> int:
    return torch.load(path, weights_only=True, map_location="cpu")["global_step"]


def test_the_final_step_is_saved_whatever_the_interval(smoke_shards, tmp_path):
    fit(smoke_shards, tmp_path / "run", max_steps=3, every=2)  # saves at 2, and at 3: the end
    assert step_of(tmp_path / "run" / "checkpoints" / "last.ckpt") == 3


def test_a_moved_run_resumes_into_its_own_last_checkpoint(smoke_shards, tmp_path):
    fit(smoke_shards, tmp_path / "run", max_steps=2, every=2)
    shutil.move(tmp_path / "run", tmp_path / "moved")
    checkpoints = tmp_path / "moved" / "checkpoints"
    fit(smoke_shards, tmp_path / "moved", max_steps=4, every=2, ckpt_path=str(checkpoints / "last.ckpt"))
    assert sorted(p.name for p in checkpoints.iterdir()) == ["last.ckpt"]  # never last-v1.ckpt
    assert step_of(checkpoints / "last.ckpt") == 4


def tampered(path: Path, change) -> None:
    """Rewrite the RunCheckpoint state stored in the checkpoint at ``path`` with ``change(state)``."""
    ckpt = torch.load(path, weights_only=True, map_location="cpu")
    (key,) = [k for k in ckpt["callbacks"] if k.startswith("RunCheckpoint")]
    change(ckpt["callbacks"][key])
    torch.save(ckpt, path)


def a_thesis(tmp_path: Path) -> Path:
    """A folder of the user's beside the run: what a resume must never delete."""
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "chapter1.tex").write_text("years of work")
    return thesis


def fit_top_k(smoke_shards, run: Path, max_steps: int, ckpt_path=None, **checkpoint) -> None:
    L.seed_everything(0)
    best = RunCheckpoint(dirpath=run / "checkpoints", every_n_train_steps=1, **checkpoint)
    trainer = make_trainer(
        max_steps, run, callbacks=[best], plugins=[AtomicCheckpointIO()], log_every_n_steps=1
    )
    trainer.fit(make_module(), make_data(smoke_shards, train_batches_per_epoch=4), ckpt_path=ckpt_path)


def test_a_stored_last_path_outside_the_checkpoint_folder_is_ignored_not_deleted(smoke_shards, tmp_path, capfd):
    """The stored ``last_model_path`` is what Lightning removes when it writes the next last.ckpt: one with
    ``..`` passes its "inside the folder" test. With the folder's own name kept, and with the run moved
    (the path rebased onto the new folder), the resume saves on and the folder two levels up survives."""
    thesis = a_thesis(tmp_path)
    run = tmp_path / "work" / "run"
    fit(smoke_shards, run, max_steps=2, every=2)
    checkpoints = run / "checkpoints"

    def escape(state):
        state["last_model_path"] = f"{state['dirpath']}/../../../thesis"

    tampered(checkpoints / "last.ckpt", escape)
    fit(smoke_shards, run, max_steps=4, every=2, ckpt_path=str(checkpoints / "last.ckpt"))
    assert (thesis / "chapter1.tex").read_text() == "years of work"
    assert step_of(checkpoints / "last.ckpt") == 4
    err = capfd.readouterr().err
    assert "aesplat fit: the checkpoint's saved state names paths that are not files in" in err
    assert "ignored, never deleted" in err and "thesis" in err

    moved = tmp_path / "work" / "moved"  # the rebased route: the stored folder differs from the new one
    shutil.move(run, moved)
    tampered(moved / "checkpoints" / "last.ckpt", escape)
    fit(smoke_shards, moved, max_steps=6, every=2, ckpt_path=str(moved / "checkpoints" / "last.ckpt"))
    assert (thesis / "chapter1.tex").read_text() == "years of work"
    assert step_of(moved / "checkpoints" / "last.ckpt") == 6


def test_a_stored_top_k_path_outside_the_checkpoint_folder_is_ignored_not_deleted(smoke_shards, tmp_path):
    """``best_k_models`` and ``kth_best_model_path``: the checkpoint that falls out of the top k is removed.
    Here the stored worst one is a folder outside the run, and the resume saves a better score."""
    thesis = a_thesis(tmp_path)
    run = tmp_path / "work" / "run"
    top = {"monitor": "train/loss", "mode": "min", "save_top_k": 1}
    fit_top_k(smoke_shards, run, max_steps=2, **top)
    (saved,) = (run / "checkpoints").glob("*.ckpt")

    def escape(state):
        outside = f"{state['dirpath']}/../../../thesis"
        state["best_k_models"] = {outside: torch.tensor(1e9)}
        state["kth_best_model_path"], state["kth_value"] = outside, torch.tensor(1e9)
        state["best_model_path"], state["best_model_score"] = outside, torch.tensor(1e9)

    tampered(saved, escape)
    fit_top_k(smoke_shards, run, max_steps=4, ckpt_path=str(saved), **top)
    assert (thesis / "chapter1.tex").read_text() == "years of work"
    assert len(list((run / "checkpoints").glob("*.ckpt"))) >= 1


def test_a_stored_previous_path_outside_the_folder_is_ignored_without_a_monitor(smoke_shards, tmp_path):
    """With nothing monitored and ``save_top_k=1`` Lightning removes the previous ``best_model_path``."""
    thesis = a_thesis(tmp_path)
    run = tmp_path / "work" / "run"
    fit_top_k(smoke_shards, run, max_steps=2, save_top_k=1)
    (saved,) = (run / "checkpoints").glob("*.ckpt")
    tampered(saved, lambda state: state.update(best_model_path=f"{state['dirpath']}/../../../thesis"))
    fit_top_k(smoke_shards, run, max_steps=4, ckpt_path=str(saved), save_top_k=1)
    assert (thesis / "chapter1.tex").read_text() == "years of work"


def test_only_files_directly_in_the_checkpoint_folder_are_kept(tmp_path, capsys):
    folder = tmp_path / "run" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / "epoch=0-step=2.ckpt").write_bytes(b"x")
    (folder / "sub").mkdir()
    (folder / "link.ckpt").symlink_to(tmp_path)
    kept = f"{folder}/epoch=0-step=2.ckpt"
    callback = RunCheckpoint(dirpath=folder, monitor="val/psnr", mode="max", save_top_k=2)
    callback.load_state_dict(
        {
            "dirpath": str(folder),
            "best_model_score": torch.tensor(3.0),
            "best_model_path": kept,
            "best_k_models": {
                kept: torch.tensor(3.0),
                f"{folder}/sub": torch.tensor(2.0),
                f"{folder}/link.ckpt": torch.tensor(1.0),
                "/etc": torch.tensor(0.5),
            },
            "kth_best_model_path": "/etc",
            "kth_value": torch.tensor(0.5),
            "last_model_path": f"{folder}/../checkpoints/last.ckpt",
        }
    )
    assert callback.best_k_models == {kept: torch.tensor(3.0)}
    assert (callback.best_model_path, callback.kth_best_model_path) == (kept, kept)
    assert callback.last_model_path == ""
    (line,) = capsys.readouterr().err.splitlines()
    assert "'/etc'" in line and "and 1 more" in line
