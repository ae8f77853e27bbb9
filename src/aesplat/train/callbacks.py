"""Training callbacks: throughput (samples and steps per second, peak memory), the run folder's checkpoints
(always a final save; a moved folder resumes into its own ``last.ckpt``) and the data record each checkpoint
carries."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.callbacks import ModelCheckpoint

from aesplat.types import DATA_RECORD


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


class RunCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` for a run folder (``checkpoint``: best by ``val/psnr``; ``last_checkpoint``:
    ``last.ckpt`` every N steps), with what a run needs besides:

    - the final step is always saved (``save_last``): when ``trainer.max_steps`` is reached, when the run is
      asked to stop (a signal, the skipped-step guard) and at the end of a fit that ended otherwise, so
      ``last.ckpt`` always holds where training stopped, whatever the save interval;
    - a run folder that was moved or copied resumes into its own ``last.ckpt`` (Lightning compares the folder
      path stored in the checkpoint with the new one and, when they differ, forgets its files and saves
      ``last-v1.ckpt``): the stored paths are moved to the new folder, and file names never get a version
      suffix (``enable_version_counter`` defaults to False: a run folder holds one run).
    """

    def __init__(self, *args: Any, enable_version_counter: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, enable_version_counter=enable_version_counter, **kwargs)

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        final = trainer.should_stop or (trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps)
        if final:
            self._save_final(trainer)

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._save_final(trainer)

    def _save_final(self, trainer: Trainer) -> None:
        if (
            not self.save_last
            or trainer.global_step == 0
            or self._last_global_step_saved == trainer.global_step
        ):
            return
        if trainer.sanity_checking or bool(trainer.fast_dev_run):
            return
        self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        saved = state_dict.get("dirpath")
        if saved and self.dirpath and Path(saved) != Path(self.dirpath):
            state_dict = _moved(state_dict, str(saved), str(self.dirpath))
        if self.dirpath:
            state_dict = _files_in(state_dict, Path(self.dirpath))
        super().load_state_dict(state_dict)
        if self.best_k_models:  # the worst kept checkpoint is the next to go, as Lightning would have set it
            worst = max if self.mode == "min" else min
            self.kth_best_model_path = worst(self.best_k_models, key=self.best_k_models.get)
            self.kth_value = self.best_k_models[self.kth_best_model_path]


def _moved(state: dict[str, Any], old: str, new: str) -> dict[str, Any]:
    """A ModelCheckpoint state with every path under folder ``old`` moved under ``new``."""

    def move(path: Any) -> Any:
        if not isinstance(path, str) or not path:
            return path
        p = Path(path)
        return str(Path(new) / p.relative_to(old)) if p.is_relative_to(old) else path

    out = {key: move(value) for key, value in state.items()}
    out["dirpath"] = new
    if isinstance(state.get("best_k_models"), dict):
        out["best_k_models"] = {move(k): v for k, v in state["best_k_models"].items()}
    return out


# The stored paths that ModelCheckpoint may later delete (a replaced last.ckpt, a checkpoint that fell out of
# the top k, the previous checkpoint when nothing is monitored) or load (``--ckpt_path best``).
_STORED_PATHS = ("best_model_path", "kth_best_model_path", "last_model_path")


def _files_in(state: dict[str, Any], folder: Path) -> dict[str, Any]:
    """``state`` keeping only the stored paths that name a file directly inside ``folder``; one warning line
    names what was dropped.

    A checkpoint is data: Lightning deletes these paths recursively when it replaces or demotes them, and its
    test for "inside the folder" does not normalise ``..``. A path with ``..``, a link, a folder, or anything
    that resolves outside ``folder`` is forgotten (as if that checkpoint had never been saved), never deleted.
    """
    dropped: list[str] = []

    def keep(path: Any) -> str | None:
        if path == "" or path is None:
            return None
        inside = _file_directly_in(path, folder) if isinstance(path, str) else None
        if inside is None:
            dropped.append(str(path))
        return inside

    out = dict(state)
    for key in _STORED_PATHS:
        if key in out:
            out[key] = keep(out[key]) or ""
    best_k = out.get("best_k_models")
    if isinstance(best_k, dict):
        out["best_k_models"] = {p: v for k, v in best_k.items() if (p := keep(k))}
    elif best_k is not None:
        dropped.append(repr(best_k))
        out["best_k_models"] = {}
    if dropped:
        dropped = list(dict.fromkeys(dropped))
        more = f" and {len(dropped) - 3} more" if dropped[3:] else ""
        names = ", ".join(repr(p) for p in dropped[:3]) + more
        where = f"the checkpoint's saved state names paths that are not files in {folder}"
        print(f"aesplat fit: {where}; ignored, never deleted: {names}", file=sys.stderr)
    return out


def _file_directly_in(path: str, folder: Path) -> str | None:
    """``folder/NAME`` when ``path`` is that file (or a file not written yet) by name, without ``..`` or a
    link on the way; else None."""
    p = Path(path)
    if "://" in path or ".." in p.parts or p.parent != folder or p.is_symlink():
        return None
    if p.exists() and not p.is_file():
        return None
    if p.parent.resolve() != folder.resolve():
        return None
    return str(folder / p.name)


class DataRecord(Callback):
    """Store the run's ``data.image_size`` in every checkpoint (key ``aesplat.types.DATA_RECORD``), so
    a checkpoint copied out of its run folder still says what input it expects (``aesplat predict``)."""

    def on_save_checkpoint(self, trainer: Trainer, pl_module: LightningModule, checkpoint: dict[str, Any]):
        image_size = getattr(trainer.datamodule, "image_size", None)
        if isinstance(image_size, int):
            checkpoint[DATA_RECORD] = {"image_size": image_size}
