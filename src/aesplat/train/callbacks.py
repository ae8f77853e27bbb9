"""Training callbacks: throughput (samples and steps per second, peak memory)."""

from __future__ import annotations

import resource
import sys
import time

import torch
from lightning.pytorch import Callback, LightningModule, Trainer


class Throughput(Callback):
    """Log ``train/samples_per_sec``, ``train/sec_per_step`` (averaged over the last ``window`` steps) and
    ``train/peak_memory_gib`` (CUDA: the most memory the caching allocator handed out; CPU: the process's peak
    resident set).

    Windows follow one another without gaps, so a window's time includes everything the loop does between steps
    (data wait, logging, callbacks). Samples are counted on this rank and multiplied by the world size (every
    rank gets the same batch size). The values are host tensors: logging them reads nothing from the device.
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
        now = time.perf_counter()
        elapsed = max(now - self._start, 1e-9)
        values = {
            "train/samples_per_sec": self._samples / elapsed,
            "train/sec_per_step": elapsed / self._steps,
            "train/peak_memory_gib": peak_memory_gib(pl_module.device),
        }
        for key, value in values.items():
            pl_module.log(key, torch.tensor(value, dtype=torch.float64), batch_size=batch.batch_size)
        self._start, self._steps, self._samples = now, 0, 0


def peak_memory_gib(device: torch.device) -> float:
    """Peak memory of this process so far: CUDA allocations on ``device``, else the resident set (GiB)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return rss / (2**30 if sys.platform == "darwin" else 2**20)
