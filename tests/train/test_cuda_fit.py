"""A short GPU fit as the paper trains (gsplat backend, bf16-mixed) with a tiny network (`make test-gpu`)."""

import lightning as L
import pytest
import torch
from lightning.pytorch import Callback

from aesplat.render import gsplat_available, interface
from tests.train.helpers import make_data, make_module

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat"),
    pytest.mark.filterwarnings("ignore:LPIPS metric unavailable"),
]

STEPS = 12


class RecordLosses(Callback):
    """The loss each training step returned, and whether every parameter was on the GPU at its end."""

    def __init__(self) -> None:
        self.losses: list[float] = []
        self.on_gpu: list[bool] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        self.losses.append(float(loss))
        self.on_gpu.append(all(p.is_cuda for p in pl_module.parameters()))


def test_cuda_fit_with_gsplat_in_bf16_has_finite_losses_and_skips_nothing(smoke_shards, tmp_path, monkeypatch):
    if not torch.cuda.is_bf16_supported():
        pytest.skip("this GPU has no bf16")
    calls = {"gsplat": 0, "torch": 0}
    for name, backend in list(interface.BACKENDS.items()):

        def counted(*args, _name=name, _backend=backend, **kwargs):
            calls[_name] += 1
            return _backend(*args, **kwargs)

        monkeypatch.setitem(interface.BACKENDS, name, counted)

    L.seed_everything(0)
    module = make_module(render={"backend": "gsplat"})
    data = make_data(smoke_shards, image_size=56, batch_size=2, train_batches_per_epoch=STEPS)
    before = [p.detach().clone() for p in module.model.parameters()]
    record = RecordLosses()
    trainer = L.Trainer(accelerator="gpu", devices=1, precision="bf16-mixed", max_steps=STEPS, logger=False,
                        callbacks=[record], enable_progress_bar=False, enable_model_summary=False,
                        enable_checkpointing=False, num_sanity_val_steps=0, limit_val_batches=0,
                        default_root_dir=str(tmp_path))  # fmt: skip
    trainer.fit(module, data)

    assert trainer.global_step == STEPS and len(record.losses) == STEPS
    assert all(torch.isfinite(torch.tensor(record.losses))), record.losses
    assert module.skipped_steps == 0, module.skip_guard.first_report
    assert not list(tmp_path.glob("nonfinite_step*.txt"))
    assert calls == {"gsplat": STEPS, "torch": 0}, "every training render must go through gsplat"
    # Lightning's teardown moves the module back to the CPU after fit: where it trained is recorded per step.
    assert record.on_gpu == [True] * STEPS, "a training step ran with parameters off the GPU"
    after = list(module.model.parameters())
    assert all(torch.isfinite(p).all() for p in after)
    changed = sum(not torch.equal(a.cpu(), b.cpu()) for a, b in zip(before, after))
    assert changed > 0.5 * len(after), f"only {changed} of {len(after)} parameters changed"
