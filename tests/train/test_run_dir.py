"""Run directories: the wandb run id is fixed per directory, wandb mode, one fit at a time (the lock), and a fit
that stops before its first checkpoint takes back what it wrote."""

import pytest

from aesplat.errors import UserError
from aesplat.train.run_dir import FitWrites, lock_run, run_artifacts, unlock_run, wandb_mode, wandb_run_id
from tests.train.helpers import hold_lock


def test_wandb_run_id_is_created_once_per_directory(tmp_path):
    first = wandb_run_id(tmp_path / "run")
    assert first == wandb_run_id(tmp_path / "run")
    assert first != wandb_run_id(tmp_path / "other")
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["wandb_run_id"], "no temporary files left behind"


def test_wandb_mode_environment_wins(monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    assert wandb_mode("online") == "offline"
    monkeypatch.delenv("WANDB_MODE")
    assert wandb_mode("disabled") == "disabled"
    # An unreachable server means offline (a reserved TEST-NET address never answers).
    assert wandb_mode("auto", host="192.0.2.1", timeout=0.2) == "offline"


def test_a_second_fit_in_a_run_folder_is_refused_while_the_first_trains(tmp_path):
    run = tmp_path / "run"
    holder, conn = hold_lock(run)
    try:
        holder_line = rf"aesplat fit \(pid {holder.pid} on .*\) is training there"
        with pytest.raises(UserError, match=rf"{run} is in use: {holder_line}"):
            lock_run(run)
    finally:
        conn.send_bytes(b"done")
        holder.join(timeout=60)
    lock_run(run)  # the first has ended: its lock went with it
    unlock_run(run)


def test_a_fit_that_never_saved_takes_back_what_it_wrote(tmp_path):
    run = tmp_path / "run"
    writes = FitWrites(run)
    lock_run(run)
    writes.snapshot()
    (run / "config.yaml").write_text("model: {}")
    (run / "wandb_run_id").write_text("abc\n")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / ".last.ckpt.ab12.partial").write_bytes(b"half")
    assert writes.discard_if_untrained() == ["config.yaml", "wandb_run_id"]
    assert not run.exists()  # it did not exist before this fit, and nothing else is in it


def test_what_a_failure_leaves_to_read_stays(tmp_path):
    """The run markers go; the wandb logs and a non-finite step's report, which the error points at, stay."""
    run = tmp_path / "run"
    writes = FitWrites(run)
    run.mkdir()
    writes.snapshot()
    (run / "config.yaml").write_text("model: {}")
    (run / "wandb").mkdir()
    (run / "nonfinite_step0.txt").write_text("the operation that went NaN")
    assert writes.discard_if_untrained() == ["config.yaml"]
    assert sorted(p.name for p in run.iterdir()) == ["nonfinite_step0.txt", "wandb"]
    assert run_artifacts(run) == []  # nothing left that refuses the corrected command


def test_a_fit_with_a_checkpoint_or_an_earlier_run_keeps_them(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("the user's")
    writes = FitWrites(run)
    (run / "config.yaml").write_text("model: {}")
    assert writes.discard_if_untrained() == ["config.yaml"]
    assert [p.name for p in run.iterdir()] == ["notes.txt"]
    (run / "config.yaml").write_text("model: {}")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.ckpt").write_bytes(b"a checkpoint")
    assert writes.discard_if_untrained() == [] and (run / "config.yaml").exists()
