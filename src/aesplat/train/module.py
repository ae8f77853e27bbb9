"""The LightningModule: wires the model, the rasterizer, the loss, the optimizer and the metrics together.

A batch flows: context + target images -> model (masked attention: targets cannot change the Gaussians)
-> Gaussians and *predicted* cameras of all views -> render the target views with the predicted target
cameras -> photometric loss against the real target images. Ground-truth poses are used only in metrics.
With ``cameras="dataset"`` (posed training, not the method) the batch's own cameras replace the camera
head's everywhere; the head is frozen and never runs, unless ``loss.pose_weight`` > 0 (the posed warm start):
then it runs on all views and learns from a supervised camera loss.

Optimization is manual so that a step with a non-finite loss or gradient is visibly skipped (parameters and
AdamW state untouched, counted, logged) while the trainer's step counter, the schedule and the curriculum
advance with the batch; ``SkipGuard`` explains the first such step and stops a run whose skips are not rare.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from lightning.pytorch import LightningModule
from lightning.pytorch.loggers import WandbLogger
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor
from torchmetrics import MeanMetric

from aesplat.data.sampler import ContextCount
from aesplat.errors import UserError
from aesplat.files import name_digest
from aesplat.images import save_image
from aesplat.model import (
    CAMERA_SOURCES,
    CameraSource,
    ModelOutput,
    NetConfig,
    checkpoint_cameras,
    dataset_cameras,
    forward_batch,
)
from aesplat.model.nas3r import convert_nas3r_state, is_nas3r_state
from aesplat.render import RasterizerConfig, render
from aesplat.types import BatchedExample, Gaussians, RenderOutput, StepTracker

from .evaluation import EvalConfig, pose_auc_scalars, visual_grid, write_results
from .loss import LossConfig, PhotometricLoss, camera_loss, maybe_lpips
from .metrics import context_pose_errors, highlight_psnr, overlap_bucket, psnr, relative_pose_errors, ssim
from .optim import OptimConfig, build_optimizer, clip_and_check, current_learning_rates, skipped_when
from .rng import restore_rng_state, rng_state
from .skip_guard import SkipGuard
from .splat_metrics import fusion_gain, gaussian_shares, transfer_gain


class AESplatModule(LightningModule):
    """Pose-free feed-forward 3DGS training and evaluation (AESplat)."""

    def __init__(
        self,
        net: NetConfig | None = None,
        loss: LossConfig | None = None,
        optim: OptimConfig | None = None,
        render: RasterizerConfig | None = None,
        eval: EvalConfig | None = None,
        cameras: CameraSource = "predicted",
    ) -> None:
        """Each config is a dataclass (or its dict form, as stored in checkpoints); None = defaults.
        ``cameras``: ``predicted`` (the camera head's: the method) or ``dataset`` (each batch's own: posed)."""
        super().__init__()
        net, loss, optim, render, eval = (
            _as(NetConfig, net), _as(LossConfig, loss), _as(OptimConfig, optim),
            _as(RasterizerConfig, render), _as(EvalConfig, eval),
        )  # fmt: skip
        if cameras not in CAMERA_SOURCES:
            raise ValueError(f"model.cameras must be one of {', '.join(CAMERA_SOURCES)}, got {cameras!r}")
        configs = {"net": net, "loss": loss, "optim": optim, "render": render, "eval": eval}
        self.save_hyperparameters({**{name: asdict(cfg) for name, cfg in configs.items()}, "cameras": cameras})
        self.optim_cfg, self.render_cfg, self.eval_cfg = optim, render, eval
        self.cameras = cameras
        self.automatic_optimization = False

        self.model = net.build()
        self.pose_weight, self.pose_rotation_weight = loss.pose_weight, loss.pose_rotation_weight
        if cameras == "dataset" and self.pose_weight == 0:
            self.model.camera_head.requires_grad_(False)  # out of the optimizer and of DDP's gradient sync
        if loss.lpips_weight > 0 or eval.metrics_lpips:
            lpips, self.lpips_unavailable = maybe_lpips(required=loss.lpips_weight > 0)
        else:
            lpips, self.lpips_unavailable = None, "disabled by eval.metrics_lpips: false"
        self.lpips = lpips
        self.loss_fn = PhotometricLoss(loss, lpips)
        if self.lpips_unavailable and loss.lpips_weight == 0:
            rank_zero_warn(f"LPIPS metric unavailable: {self.lpips_unavailable}")
        self.skip_guard = SkipGuard(optim)
        self.step_tracker: StepTracker | None = None  # the data module's, handed over by whoever pairs them
        self._host_batch: BatchedExample | None = None
        self.val_means = torch.nn.ModuleDict({k: MeanMetric() for k in _METRIC_KEYS})
        self._test_rows: list[dict] = []

    # ----------------------------------------------------------------------------------------- data movement
    def transfer_batch_to_device(self, batch: BatchedExample, device: torch.device, dataloader_idx: int):
        if self.training:
            self._host_batch = batch
        return batch.to(device)

    def on_after_batch_transfer(self, batch: BatchedExample, dataloader_idx: int) -> BatchedExample:
        return batch.float_images()

    # ----------------------------------------------------------------------------------------- forward
    def forward(
        self, batch: BatchedExample, with_context: bool = False, predict_cameras: bool = False
    ) -> tuple[ModelOutput, RenderOutput]:
        """Model outputs and the renders of the target views with the target cameras (``self.cameras``);
        ``with_context``: the context views first, each rendered at its own camera (one render call);
        ``predict_cameras``: with the data set's cameras, run the camera head too (``forward_batch``)."""
        first = 0 if with_context else batch.context.num_views
        height, width = batch.context.image_shape
        out = forward_batch(self.model, batch, self.cameras, predict_cameras)
        rendered = self.render(
            out.gaussians, out.extrinsics[:, first:], out.intrinsics[:, first:], height, width
        )
        return out, rendered

    def render(self, gaussians: Gaussians, extrinsics: Tensor, intrinsics: Tensor, height: int, width: int):
        """``aesplat.render.render`` with the run's rasterizer settings and background."""
        background = torch.tensor(self.render_cfg.background, device=self.device)
        return render(gaussians, extrinsics, intrinsics, height, width, background=background,
                      **self.render_cfg.render_kwargs())  # fmt: skip

    # ----------------------------------------------------------------------------------------- training
    def setup(self, stage: str) -> None:
        # Before any step: a count of context views the network cannot take is one line, not a failed step.
        for count in context_view_counts(getattr(self.trainer, "datamodule", None)):
            self.model.check_context_views(count)
        if stage in ("test", "validate") and self.trainer.world_size > 1:
            # Ranks that torchrun started each named the evaluation folder from their own clock: all write
            # into rank 0's, so one folder holds every rank's renders.
            self.eval_cfg.output_dir = self.trainer.strategy.broadcast(str(self.test_output_dir), src=0)

    def on_fit_start(self) -> None:
        warning = NetConfig(**self.hparams["net"]).random_backbone_warning()
        if warning:
            rank_zero_warn(warning)

    def training_step(self, batch: BatchedExample, batch_idx: int) -> Tensor:
        """One optimizer step. Nothing in it waits for the device except on the steps that read values back
        (``_reads_back``): the non-finite check and the skip are decided on the device (fused AdamW), and the
        logged scalars and skip flags are read in one transfer every ``trainer.log_every_n_steps`` steps."""
        step, optimizer, scheduler = self.global_step, self.optimizers(), self.lr_schedulers()
        host_batch = self._host_batch  # the batch as the loader gave it, for the anomaly re-run of a skip
        with_context = self.loss_fn.renders_context
        out, rendered = self(batch, with_context=with_context, predict_cameras=self.pose_weight > 0)
        context_pred = None
        if with_context:
            vc = batch.context.num_views
            context_pred, rendered = rendered.color[:, :vc], rendered.apply(lambda t: t[:, vc:])
        terms = self.loss_fn(rendered.color, batch.target.images, self.global_step, context_pred,
                             batch.context.images)  # fmt: skip
        if self.pose_weight > 0:  # the posed warm start: the camera head against the data set's cameras
            predicted = out.predicted_cameras or (out.extrinsics, out.intrinsics)
            pose = camera_loss(*predicted, *dataset_cameras(batch), self.pose_rotation_weight)
            terms["total"] = terms["total"] + self.pose_weight * pose.pop("total")
            terms.update({f"pose_{k}": v for k, v in pose.items()})
        optimizer.zero_grad(set_to_none=True)
        # Always backward, even on a NaN loss: under DDP every rank must join the gradient all-reduce.
        self.manual_backward(terms["total"])
        grad_norm, found_inf = clip_and_check(self.model.parameters(), self.optim_cfg.grad_clip, terms["total"])
        # Every rank takes the same decision (an all-reduce on the device, no wait).
        found_inf = self.trainer.strategy.reduce(found_inf, reduce_op="sum").clamp(max=1.0)
        rerun = None
        if self.skip_guard.explains_next_skip and host_batch is not None:
            rerun = lambda: self._rerun_loss(host_batch)  # noqa: E731
        self.skip_guard.defer(step, found_inf, rerun)
        fused = bool(optimizer.optimizer.defaults.get("fused"))
        if not fused:  # these kernels need the decision on the host anyway: account the step before it
            self._read_back(step, {})
        with skipped_when(optimizer.optimizer, found_inf):
            optimizer.step()
        scheduler.step()
        if self.step_tracker is not None:  # the data side's view-gap curriculum and its next epoch's stream
            self.step_tracker.set(self.global_step)

        if self._reads_back(step):
            scalars = {
                f"train/{'loss' if key == 'total' else key}": terms[key]
                for key in _TRAIN_SCALARS
                if key in terms
            }
            with torch.no_grad():
                psnr_ = psnr(rendered.color.flatten(0, 1), batch.target.images.flatten(0, 1)).mean()
            scalars.update({"train/psnr": psnr_, "train/grad_norm": grad_norm})
            host = self._read_back(step, scalars)  # stops the run when skipping is no longer rare
            host["train/skipped_steps"] = torch.tensor(float(self.skipped_steps))
            host["train/context_views"] = torch.tensor(float(batch.context.num_views))  # may vary by batch
            for name, lr in current_learning_rates(optimizer.optimizer).items():
                host[f"lr/{name}"] = torch.tensor(lr)
            b = batch.batch_size
            for key, value in host.items():  # host tensors: Lightning reads them without touching the device
                self.log(key, value, prog_bar=key in ("train/loss", "train/psnr"), batch_size=b)
        every = self.eval_cfg.log_images_every_n_steps
        if every > 0 and self.global_step % every == 0:
            self._log_images("train/images", batch, rendered)
        return terms["total"].detach()

    def _reads_back(self, step: int) -> bool:
        """Whether this step reads values back to the host: when Lightning writes its logs (its logger
        connector's rule: every ``trainer.log_every_n_steps`` batches, or when the run is stopping)."""
        every = self.trainer.log_every_n_steps
        return self.trainer.should_stop or (every > 0 and (step + 1) % every == 0)

    def _read_back(self, step: int | None, scalars: dict[str, Tensor]) -> dict[str, Tensor]:
        """Read ``scalars`` and the deferred skip flags to the host in one transfer, account the deferred steps
        (``SkipGuard.resolve``: count, explain, stop) and return the scalars as host tensors."""
        flags = self.skip_guard.pending_flags()
        values = [v.detach().float().reshape(()) for v in scalars.values()] + [f.reshape(()) for f in flags]
        if not values:
            return {}
        device = values[-1].device
        host = torch.stack([v.to(device) for v in values]).cpu()
        if flags:
            self.skip_guard.resolve(host[len(scalars):].tolist(), self.model, self.optimizers().optimizer,
                                    self.trainer.default_root_dir, self.global_rank, step)  # fmt: skip
        return dict(zip(scalars, host[: len(scalars)].unbind()))

    def _rerun_loss(self, host_batch: BatchedExample) -> Tensor:
        """A skipped step's loss recomputed from its batch (the anomaly re-run; forward and loss only)."""
        batch = self.on_after_batch_transfer(self.transfer_batch_to_device(host_batch, self.device, 0), 0)
        return self.loss_fn(self(batch)[1].color, batch.target.images)["total"]

    def on_train_end(self) -> None:
        self._read_back(None, {})  # the last deferred skip flags: the count is exact when fit returns

    def on_train_epoch_end(self) -> None:
        """Log the data stream's skip counters (corrupt samples / shards, curriculum rejections) per epoch."""
        datamodule = getattr(self.trainer, "datamodule", None)
        if datamodule is not None and hasattr(datamodule, "data_errors"):
            for key, count in datamodule.data_errors().items():
                self.log(f"data/{key}", float(count), rank_zero_only=True)

    # ----------------------------------------------------------------------------------------- evaluation
    def _evaluate(self, batch: BatchedExample) -> tuple[dict[str, Tensor], ModelOutput, RenderOutput]:
        """Per-scene metrics: image metrics averaged over each scene's target views, pose errors over views
        (all but view 0, and the target views alone: the same views whatever the count of context views), and
        the context views' errors of the pose AUC (``context_pose_errors``)."""
        out, rendered = self(batch)
        b, vt = batch.target.images.shape[:2]
        pred, target = rendered.color.flatten(0, 1), batch.target.images.flatten(0, 1)
        metrics = {"psnr": psnr(pred, target), "ssim": ssim(pred, target)}
        if self.lpips is not None:
            metrics["lpips"] = self.lpips(pred, target)
        metrics = {k: v.reshape(b, vt).mean(1) for k, v in metrics.items()}
        if self.cameras == "predicted":  # with the data set's cameras there is no pose error to measure
            gt = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1)
            rot, trans = relative_pose_errors(out.extrinsics, gt)
            metrics["rot_err_deg"], metrics["trans_err_deg"] = rot.mean(1), trans.mean(1)
            metrics["rot_err_target_deg"] = rot[:, -vt:].mean(1)
            metrics["trans_err_target_deg"] = trans[:, -vt:].mean(1)
            vc = batch.context.num_views
            metrics.update(context_pose_errors(out.extrinsics[:, :vc], batch.context.extrinsics))
        return metrics, out, rendered

    def _splat_metrics(
        self, batch: BatchedExample, out: ModelOutput, rendered: RenderOutput, fused_psnr: Tensor
    ) -> dict[str, Tensor]:
        """Point lattice or 3D scene (``splat_metrics``): the Gaussians' opaque and sub-pixel shares, the fusion
        gain and, with ``batch.target_large``, the resolution-transfer gain; each [B]."""
        vc = batch.context.num_views
        extrinsics, intrinsics = out.extrinsics[:, vc:], out.intrinsics[:, vc:]
        metrics = gaussian_shares(out.gaussians, out.depth, out.intrinsics[:, :vc])
        metrics["fusion_gain_db"] = fusion_gain(self.render, out.gaussians, vc, extrinsics, intrinsics,
                                                batch.target.images, fused_psnr)  # fmt: skip
        if batch.target_large is not None:
            metrics.update(transfer_gain(self.render, out.gaussians, extrinsics, intrinsics, rendered.color,
                                         batch.target_large))  # fmt: skip
        return metrics

    def validation_step(self, batch: BatchedExample, batch_idx: int) -> None:
        metrics, _, rendered = self._evaluate(batch)
        for key, values in metrics.items():
            if key in self.val_means:  # the target views' pose errors go to the test CSV only
                self.val_means[key].update(values)
        if batch_idx == 0:
            self._log_images("val/images", batch, rendered)

    def on_validation_epoch_end(self) -> None:
        for key, metric in self.val_means.items():
            if metric.update_count == 0:  # LPIPS without its weights, pose errors with the data set's cameras
                continue
            self.log(f"val/{key}", metric.compute(), prog_bar=key == "psnr", sync_dist=False)
            metric.reset()

    def test_step(self, batch: BatchedExample, batch_idx: int) -> None:
        metrics, out, rendered = self._evaluate(batch)
        if self.eval_cfg.splat_metrics:
            metrics.update(self._splat_metrics(batch, out, rendered, metrics["psnr"]))
        if batch.highlight is not None:  # highlight pixels vs the rest; a view without highlights is skipped
            b, vt = batch.highlight.shape[:2]
            split = highlight_psnr(rendered.color.flatten(0, 1), batch.target.images.flatten(0, 1),
                                   batch.highlight.flatten(0, 1))  # fmt: skip
            metrics.update({k: v.reshape(b, vt).nanmean(1) for k, v in split.items()})
        for i in range(batch.batch_size):
            overlap = None if batch.overlap is None else float(batch.overlap[i])
            row = {
                "scene": batch.scene[i] if batch.scene else f"batch{batch_idx}_{i}",
                "dataset": batch.dataset[i] if batch.dataset else "",
                "overlap": overlap,
                "bucket": overlap_bucket(overlap),
                "gap": None if batch.gap is None else int(batch.gap[i]),
                "context_views": batch.context.num_views,
                "context_frames": " ".join(str(f) for f in batch.context.index[i].tolist()),
                "target_frames": " ".join(str(f) for f in batch.target.index[i].tolist()),
                **{k: float(v[i]) for k, v in metrics.items()},
            }
            self._test_rows.append(row)
            if len(self._test_rows) <= self.eval_cfg.num_sample_renders:
                grid = visual_grid(batch.context.images[i : i + 1], batch.target.images[i : i + 1],
                                   rendered.color[i : i + 1], rendered.depth[i : i + 1])  # fmt: skip
                save_image(grid, self.test_output_dir / "renders" / render_name(row["scene"]))
        for key, values in metrics.items():
            if key not in _METRIC_KEYS:  # highlight metrics (NaN for diffuse scenes) go to the CSV only
                continue
            self.log(f"test/{key}", values.mean(), batch_size=batch.batch_size, sync_dist=True)

    def on_test_epoch_start(self) -> None:
        self._test_rows = []

    def on_test_epoch_end(self) -> None:
        rows = self._test_rows
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            gathered: list[list[dict]] = [[] for _ in range(torch.distributed.get_world_size())]
            torch.distributed.all_gather_object(gathered, rows)
            rows = [row for part in gathered for row in part]
        if not rows:  # every rank alike: an evaluation of nothing must not pass for a result
            raise UserError(f"evaluated no scene: every sample was skipped ({self._test_skips()}); see the "
                            "warnings above for each sample's reason")  # fmt: skip
        if self.trainer.is_global_zero:
            summary = write_results(rows, self.test_output_dir, self.lpips_unavailable, self.cameras)
            print(f"wrote {len(rows)} scenes to {self.test_output_dir}: {summary['metrics']}")
            for key, value in pose_auc_scalars(summary).items():  # over all ranks' scenes: rank 0 alone
                self.log(key, value, rank_zero_only=True)

    def _test_skips(self) -> str:
        """The data module's test-split skip counters that are not zero, e.g. ``too_few_targets: 4``."""
        counts = getattr(self.trainer.datamodule, "data_errors", dict)()
        named = [f"{k.split('/', 1)[1]}: {v}" for k, v in counts.items() if k.startswith("test/") and v]
        return ", ".join(named) or "no sample in the split"

    @property
    def skipped_steps(self) -> int:
        """Training steps skipped for a non-finite loss or gradient (checkpointed). Exact when read: deferred
        skip flags are read first (one host synchronisation when some are pending)."""
        if self.skip_guard.pending and self._trainer is not None:
            self._read_back(None, {})
        return self.skip_guard.total

    @property
    def test_output_dir(self) -> Path:
        if self.eval_cfg.output_dir:
            return Path(self.eval_cfg.output_dir)
        return Path(self.trainer.default_root_dir) / "test"

    # ----------------------------------------------------------------------------------------- optimizer
    def configure_optimizers(self):
        pretrained = bool(getattr(self.model, "pretrained_backbone", False))
        optimizer, scheduler = build_optimizer(
            self.model.named_parameter_groups(), self.optim_cfg, pretrained, total_steps=self.trainer.max_steps
        )
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ----------------------------------------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self._trainer is not None and self.trainer.training:
            self._read_back(None, {})  # the deferred skip flags belong to the saved counters
        checkpoint["skipped_steps"] = self.skipped_steps
        checkpoint["skip_guard"] = self.skip_guard.state_dict()
        checkpoint["rng"] = rng_state()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if is_nas3r_state(checkpoint.get("state_dict", {})):  # NAS3R's .ckpt: its network under our names
            converted, _ = convert_nas3r_state(checkpoint["state_dict"])
            own = self.state_dict()  # the appearance head (which NAS3R lacks) and the metrics keep theirs
            checkpoint["state_dict"] = {**own, **{"model." + k: v for k, v in converted.items()}}
            checkpoint.pop("loops", None)  # NAS3R's loop progress is not this run's
        if (saved := checkpoint_cameras(checkpoint)) != self.cameras:
            raise ValueError(f"the checkpoint was trained with model.cameras={saved}, this run has "
                             f"{self.cameras}; pass --model.cameras {saved}")  # fmt: skip
        self.skip_guard.load_state_dict(
            checkpoint.get("skip_guard", {"total": checkpoint.get("skipped_steps", 0)})
        )
        trainer = self._trainer  # None when loaded outside a Trainer (load_from_checkpoint)
        if checkpoint.get("rng") is not None and trainer is not None and trainer.training:
            restore_rng_state(checkpoint["rng"])

    # ----------------------------------------------------------------------------------------- logging
    def _log_images(self, key: str, batch: BatchedExample, rendered: RenderOutput) -> None:
        if not isinstance(self.logger, WandbLogger) or not self.trainer.is_global_zero:
            return
        n = min(4, batch.batch_size)
        grid = visual_grid(batch.context.images[:n], batch.target.images[:n], rendered.color[:n].detach(),
                           rendered.depth[:n].detach())  # fmt: skip
        caption = "context | target | render | rendered depth"
        self.logger.log_image(key=key, images=[grid], caption=[caption], step=self.global_step)


_METRIC_KEYS = ("psnr", "ssim", "lpips", "rot_err_deg", "trans_err_deg")
_TRAIN_SCALARS = ("total", "mse", "lpips", "context_mse", "context_lpips", "pose_rotation", "pose_translation",
                  "pose_focal")  # fmt: skip


def _as(cls, value):
    """Accept a config dataclass, a plain dict (checkpoints store hyperparameters as dicts) or None."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, dict):
        return cls(**value)
    raise TypeError(f"expected {cls.__name__} or a dict, got {type(value).__name__}")


def context_view_counts(datamodule: object) -> list[int]:
    """The numbers of context views a data module's batches bring: its ``num_context_views``, a number or an
    inclusive range ``[low, high]`` (:meth:`ContextCount.parse`); none when it has no such setting."""
    try:
        views = ContextCount.parse(getattr(datamodule, "num_context_views", None))
    except ValueError:
        return []
    return list(range(views.lo, views.hi + 1))


def render_name(scene: str) -> str:
    """The file name of a scene's render grid: the scene key itself when it is a plain, short, lower-case
    name; else its letters, digits, ``-`` and ``_`` (at most 80) and ``~`` with 8 hex digits of its hash, so
    that keys that differ only in other characters, in case (a case-insensitive file system) or beyond the
    80th character get files of their own."""
    plain = "".join(c if c.isascii() and (c.isalnum() or c in "-_.") else "_" for c in scene)
    if plain == scene.lower() and 0 < len(scene) <= 120 and not scene.startswith("."):
        return f"{scene}.png"
    return f"{plain.lstrip('.')[:80]}~{name_digest(scene)}.png"
