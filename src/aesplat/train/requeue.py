"""SLURM preemption at a step boundary: the requeue signal waits for the end of the step under way.

Lightning's SLURM auto-requeue handler (SIGUSR1: write ``hpc_ckpt_N.ckpt``, ``scontrol requeue``) runs wherever
the signal lands: in the middle of a step the checkpoint holds half a step (parameters updated but the batch
not counted, or the reverse), and under DDP each rank stops at a different point, so one rank's checkpoint
barrier meets another's gradient all-reduce. Here the signal is blocked from process start
(``aesplat.cli.hold_requeue_signal``, before any thread or DataLoader worker exists, so none of them takes it;
importing torch already starts one); after
every training step the ranks agree whether any of them has it pending, and if so all of them let it through
at the same point. Lightning's own handler then writes the HPC checkpoint where ``ModelCheckpoint`` writes
``last.ckpt`` (a state that resumes exactly) and requeues the job, and the ranks wait there for SLURM's
SIGTERM instead of training steps that the requeued job would repeat.
"""

from __future__ import annotations

import signal
import sys
import time

import torch
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

REQUEUE_SIGNAL = signal.SIGUSR1  # Lightning's SLURMEnvironment default; slurm/train.sbatch asks for it


def _held() -> bool:
    return REQUEUE_SIGNAL in signal.pthread_sigmask(signal.SIG_BLOCK, set())


class RequeueAtStepBoundary(Callback):
    """Hand a held requeue signal to Lightning's SLURM handler at the end of a training step, on all ranks.

    Args:
        wait_for_kill: seconds to wait for SLURM's SIGTERM after the requeue before training on (a requeue
            that failed: Lightning has logged why).
    """

    def __init__(self, wait_for_kill: float = 120.0) -> None:
        self.wait_for_kill = wait_for_kill
        self.active = False
        self.done = False

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        if sys.platform == "win32" or not _held():
            return
        # The environment Lightning's signal connector looks at when it installs the requeue handler.
        env = trainer._accelerator_connector.cluster_environment
        self.active = (
            stage == "fit"
            and isinstance(env, SLURMEnvironment)
            and env.auto_requeue
            and env.requeue_signal == REQUEUE_SIGNAL
        )
        if not self.active:  # nothing here requeues: the signal acts as Lightning (or the OS) would have it
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        if not self.active or self.done:
            return
        pending = REQUEUE_SIGNAL in signal.sigpending()
        flag = torch.tensor(float(pending), device=pl_module.device)
        if trainer.world_size > 1:
            flag = trainer.strategy.reduce(flag, reduce_op="sum")
        if flag.item() == 0:
            return
        self.done = True
        rank_zero_info(f"requeue signal after step {trainer.global_step}: checkpoint and requeue")
        if not pending:  # another rank got it: take the same path
            signal.raise_signal(REQUEUE_SIGNAL)
        # Unblocking delivers the pending signal, and Python runs Lightning's handler before this call returns
        # (hpc_ckpt_N.ckpt, collective on every rank; `scontrol requeue` on rank 0). Later signals stay held.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})
        signal.pthread_sigmask(signal.SIG_BLOCK, {REQUEUE_SIGNAL})
        deadline = time.monotonic() + self.wait_for_kill
        while not trainer.received_sigterm and time.monotonic() < deadline:
            time.sleep(0.2)
        if not trainer.received_sigterm:
            rank_zero_warn(f"no SIGTERM {self.wait_for_kill:g} s after the requeue: training on")
