"""Run directories: the wandb run id is fixed per directory, the newest checkpoint is found, wandb mode."""

import os
import time

from aesplat.train.run_dir import latest_checkpoint, wandb_mode, wandb_run_id


def test_wandb_run_id_is_created_once_per_directory(tmp_path):
    first = wandb_run_id(tmp_path / "run")
    assert first == wandb_run_id(tmp_path / "run")
    assert first != wandb_run_id(tmp_path / "other")
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["wandb_run_id"], "no temporary files left behind"


def test_latest_checkpoint_prefers_the_newest(tmp_path):
    assert latest_checkpoint(tmp_path) is None
    (tmp_path / "checkpoints").mkdir()
    last = tmp_path / "checkpoints" / "last.ckpt"
    last.write_text("a")
    (tmp_path / "checkpoints" / "best-step4.ckpt").write_text("b")
    assert latest_checkpoint(tmp_path) == last
    hpc = tmp_path / "hpc_ckpt_1.ckpt"
    hpc.write_text("c")
    later = time.time() + 10
    os.utime(hpc, (later, later))
    assert latest_checkpoint(tmp_path) == hpc


def test_wandb_mode_environment_wins(monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    assert wandb_mode("online") == "offline"
    monkeypatch.delenv("WANDB_MODE")
    assert wandb_mode("disabled") == "disabled"
    # An unreachable server means offline (a reserved TEST-NET address never answers).
    assert wandb_mode("auto", host="192.0.2.1", timeout=0.2) == "offline"
