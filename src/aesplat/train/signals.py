"""Signals during training, acted on at a step boundary: a stop signal saves where training stopped, the
SLURM requeue signal checkpoints and requeues.

**Stop** (SIGTERM, SIGINT, SIGHUP: ``kill``, Ctrl-C, a closed terminal, ``scancel``, a time limit): the step
under way finishes, every rank agrees to stop at the same step, ``last.ckpt`` is saved there
(``aesplat.train.callbacks.RunCheckpoint``) and the fit ends; ``aesplat fit`` then exits with 128 + the
signal's number, so ``aesplat fit … && aesplat test …`` never takes a stopped run for a finished one. A second
stop signal stops at once, without saving. (Lightning's own SIGTERM handling stops without a checkpoint and
exits 0; it is replaced while training runs.) A signal sent to the whole process group or job reaches the
data-loader workers too: they ignore it (``aesplat.errors.ignore_stop_signals_in_worker``), so the step under
way can finish.

**Requeue** (SIGUSR1 under SLURM, ``#SBATCH --signal=SIGUSR1@90``): Lightning's SLURM handler (write
``hpc_ckpt_N.ckpt``, ``scontrol requeue``) would run wherever the signal lands: in the middle of a step the
checkpoint holds half a step, and under DDP each rank stops at a different point, so one rank's checkpoint
barrier meets another's gradient all-reduce. Here the signal is blocked from process start
(``aesplat.cli.hold_requeue_signal``, before any thread or DataLoader worker exists, so none of them takes it;
importing torch already starts one); after every training step the ranks agree whether any of them has it
pending, and if so all of them let it through at the same point. Lightning's handler then writes the HPC
checkpoint where ``ModelCheckpoint`` writes ``last.ckpt`` (a state that resumes exactly) and requeues the job,
and the ranks wait there for SLURM's SIGTERM instead of training steps that the requeued job would repeat.
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import torch
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

from aesplat.errors import Stopped, heeded_signals, in_this_process_only, signal_name

REQUEUE_SIGNAL = signal.SIGUSR1  # Lightning's SLURMEnvironment default; slurm/train.sbatch asks for it


def _held() -> bool:
    return REQUEUE_SIGNAL in signal.pthread_sigmask(signal.SIG_BLOCK, set())


class SignalsAtStepBoundary(Callback):
    """Act on stop signals and on a held requeue signal at the end of a training step, on all ranks alike.

    After the fit, ``stop_signal`` is the stop signal that ended it (None if none) and ``stopped_at`` the
    global step it stopped at.

    Args:
        wait_for_kill: seconds to wait for SLURM's SIGTERM after the requeue before training on (a requeue
            that failed: Lightning has logged why).
    """

    def __init__(self, wait_for_kill: float = 120.0) -> None:
        self.wait_for_kill = wait_for_kill
        self.requeue_active = False
        self.requeued = False
        self.stop_signal: int | None = None
        self.stopped_at: int | None = None
        self._previous: dict[int, object] = {}
        self._forward = None  # passes a stop signal on to the ranks Lightning started from this process

    # ----------------------------------------------------------------------------------------- set-up
    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        if sys.platform == "win32" or not _held():
            return
        # The environment Lightning's signal connector looks at when it installs the requeue handler.
        env = trainer._accelerator_connector.cluster_environment
        self.requeue_active = (
            stage == "fit"
            and isinstance(env, SLURMEnvironment)
            and env.auto_requeue
            and env.requeue_signal == REQUEUE_SIGNAL
        )
        if not self.requeue_active:  # nothing here requeues: the signal acts as Lightning (or the OS) would
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        launcher = trainer.strategy.launcher
        self._forward = getattr(launcher, "kill", None) if launcher is not None else None
        handler = in_this_process_only(self._on_stop_signal)
        self._previous = {s: signal.signal(s, handler) for s in heeded_signals()}

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: Trainer, pl_module: LightningModule, exception: BaseException) -> None:
        self._restore()

    def _restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _on_stop_signal(self, signum: int, frame: object) -> None:
        if self.stop_signal is not None:
            raise Stopped(signum, f"stopped by a second {signal_name(signum)}, without saving")
        self.stop_signal = signum
        if self._forward is not None:
            self._forward(signum)

    # ----------------------------------------------------------------------------------------- step boundary
    def _agree(self, trainer: Trainer, pl_module: LightningModule, requeue: bool) -> tuple[bool, int]:
        """(any rank has the requeue signal pending, the stop signal any rank received or 0). One all-reduce
        under DDP; nothing leaves the host otherwise."""
        pending = requeue and REQUEUE_SIGNAL in signal.sigpending()
        stop = self.stop_signal or 0
        if trainer.world_size > 1:
            flags = torch.tensor([float(pending), float(stop)], device=pl_module.device)
            flags = trainer.strategy.reduce(flags, reduce_op="max")
            return bool(flags[0].item()), int(flags[1].item())
        return pending, stop

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        requeue, stop = self._agree(trainer, pl_module, self.requeue_active and not self.requeued)
        if requeue:
            self._requeue(trainer)
        elif stop:
            self._stop(trainer, stop)

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.state.fn != TrainerFn.FITTING or trainer.sanity_checking:
            return
        _, stop = self._agree(trainer, pl_module, requeue=False)
        if stop:
            self._stop(trainer, stop)

    def _stop(self, trainer: Trainer, signum: int) -> None:
        if self.stopped_at is not None:
            return
        self.stop_signal = self.stop_signal or signum
        self.stopped_at = trainer.global_step
        trainer.should_stop = True  # RunCheckpoint saves last.ckpt at this step; the fit then ends
        rank_zero_info(f"{signal_name(signum)} after step {trainer.global_step}: saving and stopping")

    def _requeue(self, trainer: Trainer) -> None:
        self.requeued = True
        rank_zero_info(f"requeue signal after step {trainer.global_step}: checkpoint and requeue")
        if REQUEUE_SIGNAL not in signal.sigpending():  # another rank got it: take the same path
            signal.raise_signal(REQUEUE_SIGNAL)
        # Unblocking delivers the pending signal, and Python runs Lightning's handler before this call returns
        # (hpc_ckpt_N.ckpt, collective on every rank; `scontrol requeue` on rank 0). Later signals stay held.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})
        signal.pthread_sigmask(signal.SIG_BLOCK, {REQUEUE_SIGNAL})
        deadline = time.monotonic() + self.wait_for_kill
        while self.stop_signal is None and time.monotonic() < deadline:
            time.sleep(0.2)
        if self.stop_signal is not None:  # SLURM ends this job; the requeued one resumes from hpc_ckpt_N
            raise Stopped(self.stop_signal, f"requeued after step {trainer.global_step}: the job resumes "
                          "from its hpc_ckpt file")  # fmt: skip
        rank_zero_warn(f"no SIGTERM {self.wait_for_kill:g} s after the requeue: training on")
