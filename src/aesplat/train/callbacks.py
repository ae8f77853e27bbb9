"""Training callbacks: throughput (samples and steps per second), adaptive CPU thread count."""

from __future__ import annotations

import sys
import time

import torch
from lightning.pytorch import Callback, LightningModule, Trainer

from aesplat.threads import ThreadTuner


class Throughput(Callback):
    """Log ``train/samples_per_sec`` and ``train/sec_per_step`` averaged over the last ``window`` steps.

    Samples are counted on this rank and multiplied by the world size (every rank gets the same batch size).
    """

    def __init__(self, window: int = 20) -> None:
        self.window = max(1, window)
        self._start: float | None = None
        self._steps = 0
        self._samples = 0

    def on_train_batch_start(self, trainer: Trainer, pl_module: LightningModule, batch, batch_idx: int) -> None:
        if self._start is None:
            self._start = time.perf_counter()

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        self._steps += 1
        self._samples += batch.batch_size * trainer.world_size
        if self._steps < self.window or self._start is None:
            return
        elapsed = max(time.perf_counter() - self._start, 1e-9)
        pl_module.log("train/samples_per_sec", self._samples / elapsed, batch_size=batch.batch_size)
        pl_module.log("train/sec_per_step", elapsed / self._steps, batch_size=batch.batch_size)
        self._start, self._steps, self._samples = None, 0, 0


class AdaptiveThreads(Callback):
    """Apply ``aesplat.threads.ThreadTuner`` during a fit: time each training step (batch start to batch end:
    forward, backward and optimizer; validation and checkpoint writing fall outside) and set torch's
    intra-op thread count to the tuner's choice. Prints a line whenever a round of measuring changes it."""

    def __init__(self, tuner: ThreadTuner) -> None:
        self.tuner = tuner
        self._start: float | None = None

    def on_train_batch_start(self, trainer: Trainer, pl_module: LightningModule, batch, batch_idx: int) -> None:
        self._start = time.perf_counter()

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        if self._start is None:
            return
        rounds = self.tuner.rounds
        threads = self.tuner.observe(time.perf_counter() - self._start)
        self._start = None
        if threads is not None:
            torch.set_num_threads(threads)
        if self.tuner.rounds != rounds and threads is not None and trainer.is_global_zero:
            timing = ", ".join(f"{t * 1e3:.0f} ms at {c}" for c, t in sorted(self.tuner.last_round.items()))
            print(f"aesplat: torch CPU threads: {threads} from step {trainer.global_step} (step time {timing})",
                  file=sys.stderr)  # fmt: skip

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.is_global_zero and self.tuner.rounds:
            steps = ", ".join(f"{n} at {c}" for c, n in self.tuner.steps_at.items() if n)
            print(f"aesplat: torch CPU threads during the fit: {steps} (steps at each count)", file=sys.stderr)
