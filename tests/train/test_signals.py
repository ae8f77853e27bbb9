"""Signals during training act at a step boundary: the requeue signal waits for the end of the step under way,
then Lightning's SLURM handler takes it there; a stop signal (SIGTERM, SIGINT) saves last.ckpt where training
stopped and `aesplat fit` exits with 128 + the signal.

One process, SLURM's environment variables set by hand and a fake `scontrol`: no cluster needed (the real
thing, two ranks and a requeued job, is tests/train/test_slurm_jobs.py).
"""

import os
import signal

import lightning as L
import pytest
import torch
from lightning.pytorch import Callback

from aesplat.errors import Stopped
from aesplat.train.callbacks import RunCheckpoint
from aesplat.train.signals import REQUEUE_SIGNAL, SignalsAtStepBoundary
from tests.train.helpers import SignalDuringStep, make_data, make_module, make_trainer

SLURM_TASK = {
    "SLURM_JOB_ID": "77", "SLURM_JOB_NAME": "aesplat-train", "SLURM_NTASKS": "1", "SLURM_NTASKS_PER_NODE": "1",
    "SLURM_NNODES": "1", "SLURM_NODELIST": "localhost", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
    "SLURM_NODEID": "0",
}  # fmt: skip


@pytest.fixture
def slurm_task(monkeypatch, tmp_path):
    """SLURM task variables, a `scontrol` recording its arguments, the signal held as `aesplat fit` holds it."""
    for key, value in SLURM_TASK.items():
        monkeypatch.setenv(key, value)
    calls = tmp_path / "scontrol_calls"
    fake = tmp_path / "bin" / "scontrol"
    fake.parent.mkdir()
    fake.write_text(f'#!/usr/bin/env bash\necho "$@" >> {calls}\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}:{os.environ['PATH']}")
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {REQUEUE_SIGNAL})
    yield calls
    signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    assert REQUEUE_SIGNAL not in signal.sigpending()


def test_requeue_waits_for_the_end_of_the_step(smoke_shards, tmp_path, slurm_task):
    torch.manual_seed(0)
    sender = SignalDuringStep(at=1)
    requeue = SignalsAtStepBoundary(wait_for_kill=0.5)  # no SLURM here to send SIGTERM: train on after it
    trainer = make_trainer(4, tmp_path, callbacks=[sender, requeue])
    trainer.fit(make_module(), make_data(smoke_shards))

    assert requeue.requeue_active and requeue.requeued
    assert slurm_task.read_text().split() == ["requeue", "77"]
    hpc = sorted(p.name for p in tmp_path.glob("hpc_ckpt_*.ckpt"))
    assert hpc == ["hpc_ckpt_1.ckpt"]
    ckpt = torch.load(tmp_path / hpc[0], weights_only=True, map_location="cpu")
    # The signal came during step 2 (batch 1): the checkpoint holds the state after step 2, as last.ckpt would.
    assert ckpt["global_step"] == 2
    assert (
        ckpt["loops"]["fit_loop"]["epoch_loop.batch_progress"]["total"]["completed"] == 1
    )  # batch 1: next hook
    assert sender.steps_after == [2, 3]


def test_without_slurm_the_signal_is_not_held(smoke_shards, tmp_path, slurm_task, monkeypatch):
    monkeypatch.setenv("SLURM_JOB_NAME", "bash")  # an interactive allocation: Lightning does not requeue
    requeue = SignalsAtStepBoundary()
    trainer = make_trainer(1, tmp_path, callbacks=[requeue])
    trainer.fit(make_module(), make_data(smoke_shards))
    assert not requeue.requeue_active
    assert REQUEUE_SIGNAL not in signal.pthread_sigmask(signal.SIG_BLOCK, set())


def stop_run(smoke_shards, tmp_path, sender: Callback) -> tuple[L.Trainer, SignalsAtStepBoundary]:
    torch.manual_seed(0)
    signals = SignalsAtStepBoundary()
    last = RunCheckpoint(
        dirpath=tmp_path / "checkpoints", save_last=True, save_top_k=0, every_n_train_steps=100
    )
    trainer = make_trainer(6, tmp_path, callbacks=[sender, signals, last])
    trainer.fit(make_module(), make_data(smoke_shards))
    return trainer, signals


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_finishes_the_step_saves_it_and_ends_the_fit(
    smoke_shards, tmp_path, signum, stop_signals_heeded
):
    before = signal.getsignal(signum)
    trainer, signals = stop_run(smoke_shards, tmp_path, SignalDuringStep(at=1, signum=signum))
    assert (signals.stop_signal, signals.stopped_at, trainer.global_step) == (signum, 2, 2)
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 2  # where it stopped, though the save interval is 99 steps
    assert signal.getsignal(signum) == before  # the command's own handler is back


def test_a_second_stop_signal_stops_at_once_without_saving(smoke_shards, tmp_path):
    with pytest.raises(Stopped, match="stopped by a second SIGTERM, without saving"):
        stop_run(smoke_shards, tmp_path, SignalDuringStep(at=1, signum=signal.SIGTERM, again=True))
    assert not (tmp_path / "checkpoints" / "last.ckpt").exists()
