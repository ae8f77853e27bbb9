"""Learning curves: held-out metrics at fixed step intervals, against steps and training seconds, and the
copy-the-context yardsticks they and the demo report print.

``LearningCurve`` is a callback for `aesplat fit`; ``benchmarks/learning_curves.py`` adds it to each run it
trains (``--trainer.callbacks+=curves.LearningCurve``, with ``benchmarks/`` on ``sys.path``). At step 0 (the
untrained model), every ``every_n_steps`` steps and at the last step it evaluates the model on the data module's
validation scenes (``val_*`` columns; when the shards have a validation split) and on its test scenes, exactly
as `aesplat test` scores them (``AESplatModule._evaluate``: image metrics with the run's own cameras, pose
errors against the ground truth), and rewrites a CSV with one row per point. ``train_seconds`` is the wall time
spent training (data loading, forward, backward, update, checkpoint writes), evaluation excluded; it is kept in
the checkpoints, so a resumed run continues the clock where its checkpoint left it. Rows written after the
checkpoint a run resumes from are dropped (those steps are trained again), and no finished point is evaluated
twice. The copy-the-context yardsticks (``context_copy_psnr``) are the same at every point and are repeated in
each row so that every CSV stands alone. Choices between runs are made on the ``val_*`` columns; the test
columns are reported for the chosen run (docs/validation.md).
"""

from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path

import torch
from common import write_whole
from lightning.pytorch import Callback, LightningModule, Trainer
from torch import Tensor

from aesplat.train.metrics import psnr

CURVE_COLUMNS = (
    "step", "train_seconds", "psnr", "ssim", "lpips", "rot_err_deg", "trans_err_deg", "num_scenes",
    "copy_mean_psnr", "copy_best_psnr",
    "val_psnr", "val_ssim", "val_lpips", "val_rot_err_deg", "val_trans_err_deg", "val_num_scenes",
    "val_copy_mean_psnr", "val_copy_best_psnr",
)  # fmt: skip
_METRICS = ("psnr", "ssim", "lpips", "rot_err_deg", "trans_err_deg")
# Names of the copy-the-context yardsticks, as the demo report and the learning curves print them.
COPY_MEAN, COPY_BEST = "mean of the context views", "the better context view of each scene"


def context_copy_psnr(pairs: list[tuple[Tensor, Tensor]]) -> dict[str, float]:
    """PSNR of renders that need no model, averaged like `aesplat test` (over each scene's targets, then over
    scenes): the mean of the context views, and the better of the context views for each scene.

    pairs: (context images [1, Vc, 3, H, W], target images [1, Vt, 3, H, W]) per scene.
    """
    mean_view, best_view = [], []
    for context, target in pairs:
        tgt = target[0]
        mean_view.append(psnr(context[0].mean(0, keepdim=True).expand_as(tgt), tgt).mean().item())
        best_view.append(max(psnr(view[None].expand_as(tgt), tgt).mean().item() for view in context[0]))
    return {COPY_MEAN: sum(mean_view) / len(mean_view), COPY_BEST: sum(best_view) / len(best_view)}


SPLIT_PREFIX = {"test": "", "validation": "val_"}  # the columns of each split's figures


def read_curve(path: str | Path) -> list[dict[str, float]]:
    """Rows of a learning-curve CSV as floats (NaN where a metric is unavailable); [] when there is none."""
    path = Path(path)
    if not path.is_file():
        return []
    with open(path) as f:
        rows = [{k: float(v) if v not in ("", None) else math.nan for k, v in row.items()} for row in
                csv.DictReader(f)]  # fmt: skip
    return [{k: row.get(k, math.nan) for k in CURVE_COLUMNS} for row in rows]  # older CSVs: no val_* columns


def write_curve(path: str | Path, rows: list[dict[str, float]]) -> None:
    """Write rows (CURVE_COLUMNS; NaN or missing as empty cells) whole, so an interruption never leaves half a
    curve."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=CURVE_COLUMNS)
    writer.writeheader()
    for row in rows:
        cells = {k: row.get(k, math.nan) for k in CURVE_COLUMNS}
        writer.writerow({k: "" if isinstance(v, float) and math.isnan(v) else _cell(k, v) for k, v in
                         cells.items()})  # fmt: skip
    write_whole(Path(path), text.getvalue().encode())


def _cell(key: str, value: float) -> str:
    if key in ("step", "num_scenes", "val_num_scenes"):
        return str(int(value))
    return f"{value:.6g}"


class LearningCurve(Callback):
    """Evaluate on the validation and test scenes at step 0, every ``every_n_steps`` steps and at
    ``trainer.max_steps``.

    csv_path: the curve's CSV (rewritten at each point). max_scenes: evaluate on the first this many scenes of
    each split only (None: all; the scenes are read once and kept in memory). The validation columns stay
    empty when the shards have no validation split. Single-device runs only.
    """

    def __init__(self, csv_path: str, every_n_steps: int = 500, max_scenes: int | None = None) -> None:
        if every_n_steps < 1:
            raise ValueError(f"LearningCurve every_n_steps must be >= 1, got {every_n_steps}")
        self.csv_path = Path(csv_path)
        self.every_n_steps = every_n_steps
        self.max_scenes = max_scenes
        self.train_seconds = 0.0
        self._clock: float | None = None
        self._batches: dict[str, list] = {}
        self._copy: dict[str, dict[str, float]] = {}

    # ------------------------------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, float]:
        return {"train_seconds": self.train_seconds}

    def load_state_dict(self, state_dict: dict[str, float]) -> None:
        self.train_seconds = float(state_dict["train_seconds"])

    # ------------------------------------------------------------------------------------------ hooks
    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.world_size > 1:
            raise RuntimeError("LearningCurve evaluates on one device; train learning curves with devices=1")
        step = trainer.global_step
        rows = [r for r in read_curve(self.csv_path) if r["step"] <= step]  # later rows: trained again now
        write_curve(self.csv_path, rows)
        if not any(r["step"] == step for r in rows):
            self._record(trainer, pl_module, rows)
        self._clock = time.perf_counter()

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        step = trainer.global_step
        if step % self.every_n_steps and step != trainer.max_steps:
            return
        now = time.perf_counter()
        self.train_seconds += now - (self._clock if self._clock is not None else now)
        rows = [r for r in read_curve(self.csv_path) if r["step"] < step]
        self._record(trainer, pl_module, rows)
        self._clock = time.perf_counter()

    # ------------------------------------------------------------------------------------------ evaluation
    def _split_batches(self, trainer: Trainer, split: str) -> list:
        """One split's batches, read once (the data module's loader of it, in its fixed order)."""
        if split not in self._batches:
            dm = trainer.datamodule
            loader = dm.test_dataloader() if split == "test" else dm.val_dataloader()
            batches, scenes = [], 0
            for batch in loader:
                if self.max_scenes is not None and scenes >= self.max_scenes:
                    break
                batches.append(batch)
                scenes += batch.batch_size
            if not batches:
                raise RuntimeError(f"LearningCurve: the data module's {split} split has no scenes")
            self._batches[split] = batches
        return self._batches[split]

    def _splits(self, trainer: Trainer) -> list[str]:
        has_split = getattr(trainer.datamodule, "has_split", None)
        return ["validation", "test"] if has_split is not None and has_split("validation") else ["test"]

    @torch.no_grad()
    def _record(self, trainer: Trainer, pl_module: LightningModule, rows: list[dict[str, float]]) -> None:
        """Evaluate at the current step and append the row to ``rows`` and the CSV."""
        was_training = pl_module.training
        pl_module.eval()
        devices = [pl_module.device] if pl_module.device.type == "cuda" else []
        row: dict[str, float] = {"step": trainer.global_step, "train_seconds": self.train_seconds}
        with torch.random.fork_rng(devices=devices):  # evaluating must not change the training run's RNG
            for split in self._splits(trainer):
                row.update(self._evaluate(trainer, pl_module, split))
        pl_module.train(was_training)
        if trainer.is_global_zero:
            write_curve(self.csv_path, [*rows, row])

    def _evaluate(self, trainer: Trainer, pl_module: LightningModule, split: str) -> dict[str, float]:
        """One split's columns: mean metrics per target view, the scene count and the copy yardsticks."""
        sums, counts, pairs = dict.fromkeys(_METRICS, 0.0), dict.fromkeys(_METRICS, 0), []
        for raw in self._split_batches(trainer, split):
            batch = pl_module.on_after_batch_transfer(raw.to(pl_module.device), 0)
            metrics, _, _ = pl_module._evaluate(batch)  # per scene, as `aesplat test` scores them
            for key in _METRICS:  # the curve's columns (the target views' pose errors: the test CSV's only)
                if key in metrics:
                    sums[key] += float(metrics[key].sum())
                    counts[key] += metrics[key].numel()
            if split not in self._copy:
                pairs += [(batch.context.images[i : i + 1].cpu(), batch.target.images[i : i + 1].cpu())
                          for i in range(batch.batch_size)]  # fmt: skip
        if split not in self._copy:
            self._copy[split] = context_copy_psnr(pairs)
        pre = SPLIT_PREFIX[split]
        out = {pre + k: sums[k] / counts[k] if counts[k] else math.nan for k in _METRICS}
        out.update({pre + "num_scenes": counts["psnr"], pre + "copy_mean_psnr": self._copy[split][COPY_MEAN],
                    pre + "copy_best_psnr": self._copy[split][COPY_BEST]})  # fmt: skip
        return out
