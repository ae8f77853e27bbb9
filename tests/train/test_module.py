"""The LightningModule on real (tiny) data: NaN-safe steps, overfitting one batch, exact resume."""

import warnings

import lightning as L
import pytest
import torch
from lightning.pytorch import Callback
from lightning.pytorch.callbacks import ModelCheckpoint

from aesplat.model import dataset_cameras
from aesplat.render import render
from aesplat.train import AESplatModule
from aesplat.train.metrics import psnr
from aesplat.train.optim import OptimConfig, build_optimizer
from tests.train.helpers import make_data, make_module, make_trainer


def snapshot(module: AESplatModule, optimizer) -> tuple[list, dict]:
    params = [p.detach().clone() for p in module.model.parameters()]
    state = {id(p): {k: v.clone() for k, v in s.items()} for p, s in optimizer.state.items()}
    return params, state


class PoisonGradientOnce(Callback):
    """At training batch ``at``: snapshot parameters and Adam state, make one gradient NaN via a hook."""

    def __init__(self, at: int) -> None:
        self.at = at
        self.before = None
        self.after = None
        self._handle = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if batch_idx == self.at:
            self.before = snapshot(pl_module, trainer.optimizers[0])
            param = next(p for p in pl_module.model.parameters() if p.requires_grad)
            self._handle = param.register_hook(lambda g: torch.full_like(g, float("nan")))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if batch_idx == self.at:
            self._handle.remove()
            self.after = snapshot(pl_module, trainer.optimizers[0])
            self.skipped = pl_module.skipped_steps
            self.step = trainer.global_step


def test_nan_gradient_step_is_skipped_bit_identically(smoke_shards, tmp_path):
    L.seed_everything(0)
    module, data = make_module(), make_data(smoke_shards, train_batches_per_epoch=3)
    poison = PoisonGradientOnce(at=1)
    make_trainer(3, tmp_path, callbacks=[poison]).fit(module, data)
    (params_before, state_before), (params_after, state_after) = poison.before, poison.after
    assert state_before, "Adam state must exist before the poisoned step"
    assert all(torch.equal(a, b) for a, b in zip(params_before, params_after))
    for pid, entries in state_before.items():
        assert all(torch.equal(v, state_after[pid][k]) for k, v in entries.items())
    assert poison.skipped == 1 and module.skipped_steps == 1
    assert poison.step == 2, "the skipped batch still counts as a trainer step"
    # The step after the skipped one trains normally.
    assert not all(torch.equal(a, b) for a, b in zip(params_after, module.model.parameters()))


@pytest.mark.parametrize("size", ["base", "large"])
def test_fit_warns_when_a_paper_scale_network_has_no_pretrained_weights(size):
    """The warning `aesplat fit` gives (checked on the tiny module, whose net settings say `size`)."""
    module = make_module()
    module.hparams["net"]["size"] = size
    with pytest.warns(UserWarning, match=rf"`{size}` network starts from a RANDOM backbone") as caught:
        module.on_fit_start()
    message = str(caught[0].message)
    assert "builds on VGGT" in message and "no pose learning in 600 steps" in message
    assert "--model.net.weights" in message and "Pretrained weights" in message
    for net in ({"size": size, "weights": "/data/vggt_1B.pt"}, {"size": "tiny", "weights": None}):
        module.hparams["net"].update(net)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            module.on_fit_start()  # no warning with weights, nor for the CPU-sized network


def test_overfitting_one_batch_raises_psnr(smoke_shards):
    """The model, renderer and loss can fit one batch: PSNR rises clearly within 30 steps."""
    L.seed_everything(0)
    data = make_data(smoke_shards, flip_augment=False, gap_initial=[2, 8])
    batch = next(iter(data.train_dataloader())).float_images()
    module = make_module()
    cfg = OptimConfig(lr=1e-3, appearance_lr=3e-3, warmup_steps=0, weight_decay=0.0)
    optimizer, _ = build_optimizer(module.model.named_parameter_groups(), cfg, False, total_steps=30)
    target = batch.target.images.flatten(0, 1)
    history = []
    for _ in range(30):
        _, rendered = module(batch)
        loss = module.loss_fn(rendered.color, batch.target.images)["total"]
        history.append(psnr(rendered.color.detach().flatten(0, 1), target).mean().item())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(module.parameters(), 0.5)
        optimizer.step()
    with torch.no_grad():
        final = psnr(module(batch)[1].color.flatten(0, 1), target).mean().item()
    print(f"overfit one batch: PSNR {history[0]:.2f} -> {final:.2f} dB in 30 steps")
    assert final > history[0] + 3.0


def _fit(root, tmp_path, max_steps, ckpt_path=None, checkpoint_dir=None):
    L.seed_everything(0)
    # The schedule length is fixed (not the trainer's max_steps) so the interrupted run plans the same cosine.
    module, data = make_module(optim={"total_steps": 4}), make_data(root, train_batches_per_epoch=2)
    module.step_tracker = data.step_tracker
    last = ModelCheckpoint(dirpath=checkpoint_dir, save_last=True, save_top_k=0, every_n_train_steps=2)
    callbacks = [last] if checkpoint_dir else []
    trainer = make_trainer(max_steps, tmp_path, callbacks=callbacks, enable_checkpointing=bool(checkpoint_dir))
    trainer.fit(module, data, ckpt_path=ckpt_path)
    return module, trainer


def test_resume_n_plus_m_equals_uninterrupted(smoke_shards, tmp_path):
    straight, _ = _fit(smoke_shards, tmp_path / "a", max_steps=4)
    ckpt_dir = tmp_path / "b" / "checkpoints"
    _fit(smoke_shards, tmp_path / "b", max_steps=2, checkpoint_dir=ckpt_dir)
    resumed, trainer = _fit(smoke_shards, tmp_path / "b", 4, ckpt_path=str(ckpt_dir / "last.ckpt"),
                            checkpoint_dir=ckpt_dir)  # fmt: skip
    assert trainer.global_step == 4
    assert trainer.datamodule.step_tracker.get() >= 3, "the curriculum step must be restored"
    sched = trainer.lr_scheduler_configs[0].scheduler
    assert sched.last_epoch == 4
    for (name, a), b in zip(straight.model.named_parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=lambda m, name=name: f"{name}: {m}")
    opt_a = straight.trainer.optimizers[0].state
    opt_b = trainer.optimizers[0].state
    trained = [
        (pa, pb) for pa, pb in zip(straight.model.parameters(), resumed.model.parameters()) if pa.requires_grad
    ]
    assert trained
    for pa, pb in trained:
        torch.testing.assert_close(opt_a[pa]["exp_avg_sq"], opt_b[pb]["exp_avg_sq"], rtol=1e-5, atol=1e-9)


class _RecordBatches(Callback):
    """(global step, fingerprint of the batch's images) of every training batch."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, float]] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.seen.append((trainer.global_step, round(float(batch.target.images.float().sum()), 3)))


@pytest.mark.parametrize("num_workers", [0, 2])
def test_resume_from_the_middle_of_an_epoch_continues_exactly(smoke_shards, tmp_path, num_workers):
    """A checkpoint 3 batches into a 4-batch epoch (as a SLURM requeue writes it): the resumed run sees the
    same batches in the same order as an uninterrupted one and ends with the same parameters."""

    def fit(run, max_steps, ckpt_path=None):
        L.seed_everything(0)
        module = make_module(optim={"total_steps": 6})
        data = make_data(smoke_shards, train_batches_per_epoch=4, num_workers=num_workers)
        record = _RecordBatches()
        last = ModelCheckpoint(dirpath=tmp_path / run, save_last=True, save_top_k=0, every_n_train_steps=3)
        trainer = make_trainer(max_steps, tmp_path / run, callbacks=[record, last])
        trainer.fit(module, data, ckpt_path=ckpt_path)
        return module, record.seen

    straight, seen_straight = fit("straight", 6)
    _, seen_first = fit("interrupted", 3)
    resumed, seen_resumed = fit("interrupted", 6, ckpt_path=str(tmp_path / "interrupted" / "last.ckpt"))
    assert seen_first + seen_resumed == seen_straight
    assert len({images for _, images in seen_straight}) >= 3  # the batches differ (the smoke set is small)
    for (name, a), b in zip(straight.model.named_parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=lambda m, name=name: f"{name}: {m}")


def test_checkpoint_has_no_lpips_and_loads_weights_only(smoke_shards, tmp_path):
    _fit(smoke_shards, tmp_path, max_steps=1, checkpoint_dir=tmp_path / "ckpt")
    ckpt = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True, map_location="cpu")
    assert not any("lpips" in key for key in ckpt["state_dict"])
    assert ckpt["skipped_steps"] == 0 and "rng" in ckpt
    assert ckpt["hyper_parameters"]["optim"]["appearance_lr"] == pytest.approx(3e-4)
    # The checkpoint rebuilds its module on its own (predict, bench).
    loaded = AESplatModule.load_from_checkpoint(tmp_path / "ckpt" / "last.ckpt", map_location="cpu")
    assert loaded.hparams["net"]["size"] == "tiny"
    assert all(torch.equal(v, ckpt["state_dict"][k]) for k, v in loaded.state_dict().items())


def test_dataset_cameras_render_the_targets_with_the_data_sets_poses(smoke_shards, tmp_path):
    """model.cameras=dataset: the targets are rendered with the batch's own cameras relative to context view
    0, the camera head never runs and never trains, and everything else does train."""
    L.seed_everything(0)
    module, data = make_module(cameras="dataset"), make_data(smoke_shards, train_batches_per_epoch=2)
    assert make_module().cameras == "predicted" and module.hparams["cameras"] == "dataset"
    batch = next(iter(data.train_dataloader())).float_images()
    out, rendered = module(batch)
    poses = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1).double()
    torch.testing.assert_close(
        out.extrinsics.double(), torch.linalg.inv(poses[:, :1]) @ poses, atol=1e-5, rtol=0
    )
    extrinsics, intrinsics = dataset_cameras(batch)
    assert torch.equal(out.extrinsics, extrinsics) and torch.equal(out.intrinsics, intrinsics)
    vc, (h, w) = batch.context.num_views, batch.context.image_shape
    direct = render(out.gaussians, extrinsics[:, vc:], intrinsics[:, vc:], h, w, backend="torch")
    torch.testing.assert_close(rendered.color, direct.color, atol=1e-6, rtol=0)
    rendered.color.mean().backward()  # DDP (no unused-parameter search) needs a gradient on every trainable one
    assert all(p.grad is not None for p in module.parameters() if p.requires_grad)
    module.zero_grad(set_to_none=True)

    head = module.model.camera_head
    calls = []
    head.register_forward_hook(lambda *args: calls.append(1))
    before = {name: p.detach().clone() for name, p in module.model.named_parameters()}
    make_trainer(2, tmp_path).fit(module, data)
    assert not calls
    trained = {id(p) for group in module.trainer.optimizers[0].param_groups for p in group["params"]}
    for name, p in module.model.named_parameters():
        if name.startswith("camera_head."):
            assert p.grad is None and id(p) not in trained and torch.equal(p, before[name]), name
    out = "depth_head.scratch.output_conv2.2.weight"
    assert not torch.equal(module.model.get_parameter(out), before[out])


def test_a_checkpoint_of_the_other_camera_source_is_refused():
    module = make_module()
    with pytest.raises(ValueError, match="trained with model.cameras=dataset.*--model.cameras dataset"):
        module.on_load_checkpoint({"hyper_parameters": {"cameras": "dataset"}})
    module.on_load_checkpoint({"hyper_parameters": {}})  # older checkpoints were all predicted


def test_context_weight_renders_the_context_views_and_trains_the_pose_through_them(smoke_shards):
    """model.loss.context_weight > 0: each context view is rendered from all context Gaussians at its own
    predicted camera, and that loss alone reaches the camera head (the relative pose between the context
    views gets a photometric signal of its own)."""
    L.seed_everything(0)
    module, data = make_module(loss={"context_weight": 1.0}), make_data(smoke_shards)
    batch = next(iter(data.train_dataloader())).float_images()
    out, rendered = module(batch, with_context=True)
    vc, vt = batch.context.num_views, batch.target.num_views
    assert rendered.color.shape[1] == vc + vt
    _, targets_only = module(batch)
    torch.testing.assert_close(rendered.color[:, vc:], targets_only.color, atol=1e-6, rtol=0)
    (h, w) = batch.context.image_shape
    direct = render(out.gaussians, out.extrinsics[:, :vc], out.intrinsics[:, :vc], h, w, backend="torch")
    torch.testing.assert_close(rendered.color[:, :vc], direct.color, atol=1e-6, rtol=0)
    terms = module.loss_fn(rendered.color[:, vc:], batch.target.images, 0, rendered.color[:, :vc],
                           batch.context.images)  # fmt: skip
    terms["context_mse"].backward()
    grads = [p.grad for p in module.model.camera_head.parameters() if p.grad is not None]
    assert grads and sum(g.abs().sum() for g in grads) > 0


def test_posed_warm_start_trains_the_camera_head_and_its_checkpoint_loads_as_weights(smoke_shards, tmp_path):
    """model.cameras=dataset with loss.pose_weight > 0: renders use the data set's cameras, the camera head
    runs on all views and learns from the supervised camera loss (logged), and the checkpoint becomes the
    starting point of a pose-free run through model.net.weights (all of the model, backbone rate lowered)."""
    L.seed_everything(0)
    module = make_module(cameras="dataset", loss={"pose_weight": 1.0})
    data = make_data(smoke_shards, train_batches_per_epoch=2)
    before = {name: p.detach().clone() for name, p in module.model.camera_head.named_parameters()}
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True, save_top_k=0, every_n_train_steps=2)
    trainer = make_trainer(2, tmp_path, callbacks=[ckpt], log_every_n_steps=1)  # scalars go out with the logs
    trainer.fit(module, data)
    assert {"train/pose_rotation", "train/pose_translation", "train/pose_focal"} <= set(trainer.logged_metrics)
    assert trainer.logged_metrics["train/pose_translation"] > 0
    changed = [n for n, p in module.model.camera_head.named_parameters() if not torch.equal(p, before[n])]
    assert changed  # the head trained (it is frozen when pose_weight is 0: see the test above)

    path = tmp_path / "ckpt" / "last.ckpt"
    pose_free = make_module(net={"weights": str(path)})
    assert pose_free.cameras == "predicted" and pose_free.model.weights_report.format == "aesplat"
    assert pose_free.model.pretrained_backbone
    for name, value in module.model.state_dict().items():
        assert torch.equal(pose_free.model.state_dict()[name], value), name
    with pytest.raises(ValueError, match="trained with model.net"):
        make_module(net={"weights": str(path), "sh_degree": 1})  # another architecture: a clear error
