"""The DataModule under a real Lightning Trainer: batches move to the device, the step drives the curriculum,
checkpoints carry the curriculum state."""

from __future__ import annotations

import lightning as L
import torch

from aesplat.data import DataModule
from aesplat.types import BatchedExample, StepTracker

from .conftest import SIZE


class Probe(L.LightningModule):
    """The smallest module that consumes ``BatchedExample`` like the real one does."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(3))
        self.gaps: list[tuple[int, list[int]]] = []
        self.step_tracker = StepTracker()  # replaced by the data module's

    def on_train_batch_start(self, batch: BatchedExample, batch_idx: int) -> None:
        self.step_tracker.set(self.global_step)

    def training_step(self, batch: BatchedExample, batch_idx: int) -> torch.Tensor:
        assert isinstance(batch, BatchedExample)
        batch = batch.float_images()
        assert batch.context.images.dtype == torch.float32 and batch.context.images.max() <= 1.0
        self.gaps.append((self.global_step, batch.gap.tolist()))
        colour = batch.target.images.mean(dim=(0, 1, 3, 4))
        return ((colour - self.weight) ** 2).sum()

    def validation_step(self, batch: BatchedExample, batch_idx: int) -> None:
        self.log("val/probe", batch.float_images().target.images.mean(), batch_size=batch.batch_size)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_fit_and_resume_restore_the_curriculum(synthetic_shards, tmp_path):
    def make_dm() -> DataModule:
        return DataModule(root=str(synthetic_shards), image_size=SIZE, batch_size=2, num_workers=0,
                          gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=4,
                          train_batches_per_epoch=3, shuffle_buffer=4)  # fmt: skip

    def trainer(steps: int) -> L.Trainer:
        return L.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path, num_sanity_val_steps=0,
                         limit_val_batches=2)  # fmt: skip

    def allowed_near(step: int, gap: int) -> bool:
        # Each batch is drawn for the step it is trained at, however far ahead it was fetched.
        return dm.curriculum.accepts(gap, step)

    dm, probe = make_dm(), Probe()
    probe.step_tracker = dm.step_tracker
    trainer(4).fit(probe, datamodule=dm)
    assert all(allowed_near(step, g) for step, gaps in probe.gaps for g in gaps)
    assert all(g <= 3 for g in probe.gaps[0][1])  # the first batch: the initial range
    ckpt = next(tmp_path.rglob("*.ckpt"))
    state = torch.load(ckpt, weights_only=False)
    assert state["DataModule"]["global_step"] == 3  # set at the start of the last step

    resumed_dm, resumed = make_dm(), Probe()
    resumed.step_tracker = resumed_dm.step_tracker
    trainer(6).fit(resumed, datamodule=resumed_dm, ckpt_path=ckpt)
    assert resumed_dm.step_tracker.get() == 5
    assert [s for s, _ in resumed.gaps] == [4, 5]
    assert all(allowed_near(step, g) for step, gaps in resumed.gaps for g in gaps)
    assert all(g >= 5 for _, gaps in resumed.gaps for g in gaps)  # resumed near the end of the warm-up


def test_stream_epochs_follow_the_trainers_limit_on_training_batches():
    dm = DataModule(root="unused", image_size=SIZE, train_batches_per_epoch=10)
    assert dm.epoch_length() == 10  # no trainer
    for limit, expected in ((4, 4), (25, 10), (0.5, 5), (1.0, 10), (0.01, 1)):
        dm.trainer = L.Trainer(limit_train_batches=limit, accelerator="cpu", logger=False)
        assert dm.epoch_length() == expected, limit
