"""Training callbacks: throughput (samples and steps per second)."""

from __future__ import annotations

import time

from lightning.pytorch import Callback, LightningModule, Trainer


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
