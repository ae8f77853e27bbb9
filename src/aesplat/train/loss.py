"""Photometric loss λ_mse·MSE + λ_lpips·LPIPS(VGG) on target views, and the frozen LPIPS network.

Two options widen what the loss tells the pose head (both off by default, the paper's loss):
``context_weight`` adds the same photometric loss on the context views, each rendered from the Gaussians of
all context views at its own camera, so the relative pose between the context views gets a signal of its
own; ``blur_sigma`` / ``blur_steps`` compare blurred images early in training (coarse to fine), the blur
shrinking linearly to none, which widens the basin of the pose gradient.

``pose_weight`` adds a *supervised* camera loss (``camera_loss``: the camera head's relative poses and focal
lengths against the data set's). It is not the method, which never sees a pose: it is the posed warm start
(``conf/warmstart.yaml``), the small-scale analogue of the pose- and depth-supervised pre-training of the 3D
foundation model (VGGT) that the method starts from.

The LPIPS network is torchmetrics' implementation (its linear layers ship inside torchmetrics). Its VGG16
backbone needs torchvision's ImageNet weights, which are read from the local torch hub cache and never
downloaded. The network is held outside the module tree on purpose: it is never trained, never moved by an
optimizer and never written into a checkpoint.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .metrics import rotation_angle_deg

VGG16_FILE = "vgg16-397923af.pth"  # torchvision's VGG16_Weights.IMAGENET1K_V1


@dataclass
class LossConfig:
    """Loss weights; ``lpips_weight: 0`` opts out of LPIPS (then the VGG weights are optional)."""

    mse_weight: float = 1.0  # weight of the MSE between render and target image
    lpips_weight: float = 0.05  # weight of LPIPS (VGG16); 0 opts out, then its weights are optional
    context_weight: float = 0.0  # > 0: also render the context views and add their loss with this weight
    blur_sigma: float = 0.0  # coarse to fine: Gaussian blur (pixels) of render and image at step 0 ...
    blur_steps: int = 0  # ... shrinking linearly to no blur at this step
    pose_weight: float = 0.0  # > 0: supervise the camera head with the data set's cameras (warm start only)
    pose_rotation_weight: float = 1.0  # weight of the rotation term (radians) inside that camera loss

    def __post_init__(self) -> None:
        values = (
            self.context_weight,
            self.blur_sigma,
            self.blur_steps,
            self.pose_weight,
            self.pose_rotation_weight,
        )
        if min(values) < 0:
            raise ValueError(
                "model.loss.context_weight, blur_sigma, blur_steps, pose_weight and pose_rotation_weight "
                f"must be >= 0, got {', '.join(str(v) for v in values)}"
            )
        if self.blur_sigma > 0 and self.blur_steps == 0:
            raise ValueError("model.loss.blur_sigma > 0 needs blur_steps > 0: the step where the blur ends")

    def blur_at(self, step: int) -> float:
        """Blur sigma (pixels) of the coarse-to-fine schedule at a training step; 0 from ``blur_steps`` on."""
        if self.blur_steps <= 0:
            return 0.0
        return self.blur_sigma * max(0.0, 1.0 - step / self.blur_steps)


class LpipsWeightsMissing(FileNotFoundError):
    """The VGG16 ImageNet weights LPIPS needs are not in the local torch hub cache."""


def vgg16_weights_path() -> Path:
    """Where torchvision keeps VGG16's ImageNet weights: ``$TORCH_HOME/hub/checkpoints/vgg16-397923af.pth``."""
    return Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILE


def _missing_message(path: Path) -> str:
    return (
        f"LPIPS needs torchvision's VGG16 ImageNet weights, but {path} does not exist. Place the file "
        f"{VGG16_FILE} (from https://download.pytorch.org/models/{VGG16_FILE}) in the directory {path.parent} "
        "(the torch hub cache: $TORCH_HOME/hub/checkpoints, TORCH_HOME defaults to ~/.cache/torch), or opt "
        "out of LPIPS with `--model.loss.lpips_weight 0` (`loss.lpips_weight: 0` in the config); the LPIPS "
        "metric is then reported as unavailable. Nothing is downloaded at run time."
    )


@contextlib.contextmanager
def _no_downloads(path: Path):
    """Turn any attempt by torch.hub to fetch a file into the missing-weights error instead."""
    original = torch.hub.download_url_to_file

    def refuse(url: str, dst: str, *args, **kwargs) -> None:
        raise LpipsWeightsMissing(_missing_message(path))

    torch.hub.download_url_to_file = refuse
    try:
        yield
    finally:
        torch.hub.download_url_to_file = original


def load_lpips_network() -> nn.Module:
    """torchmetrics' LPIPS(VGG) network in eval mode with frozen weights, loaded without any download.

    Raises LpipsWeightsMissing (naming the file, the directory and the opt-out) before building anything
    when the VGG16 weights are absent.
    """
    path = vgg16_weights_path()
    if not path.is_file():
        raise LpipsWeightsMissing(_missing_message(path))
    from torchmetrics.functional.image.lpips import _NoTrainLpips

    with _no_downloads(path):
        # Random backbone first (no download); the linear calibration layers load from torchmetrics' package.
        net = _NoTrainLpips(net="vgg", pretrained=True, pnet_rand=True)
        state = torch.load(path, map_location="cpu", weights_only=True)
    features = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
    slices = [f"slice{i}" for i in range(1, 6)]
    slice_of = {name: s for s in slices for name, _ in getattr(net.net, s).named_children()}
    mapped = {f"{slice_of[k.split('.')[0]]}.{k}": v for k, v in features.items() if k.split(".")[0] in slice_of}
    net.net.load_state_dict(mapped, strict=True)
    net.requires_grad_(False)
    return net.eval()


class FrozenLpips:
    """LPIPS between images in [0, 1]; the network follows the input's device and is never registered.

    ``lpips(pred, target)`` with pred, target [N, 3, H, W] -> [N] distances (lower is better).
    """

    def __init__(self, net: nn.Module) -> None:
        self._net = net

    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        if next(self._net.parameters()).device != pred.device:
            self._net.to(pred.device)
        with torch.autocast(pred.device.type, enabled=False):
            out = self._net(pred.float(), target.float(), normalize=True)
        return out.reshape(pred.shape[0])


def maybe_lpips(required: bool) -> tuple[FrozenLpips | None, str | None]:
    """LPIPS when its weights are present; if not, raise when ``required`` else return (None, reason)."""
    try:
        return FrozenLpips(load_lpips_network()), None
    except LpipsWeightsMissing:
        if required:
            raise
        return None, f"VGG16 weights not found at {vgg16_weights_path()}"


def gaussian_blur(images: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur with reflected borders: images [N, C, H, W] -> [N, C, H, W]; sigma in pixels
    (the kernel is cut at 3 sigma and at the image size); sigma <= 0 returns the images unchanged."""
    if sigma <= 0:
        return images
    n, c, h, w = images.shape
    radius = max(1, min(int(math.ceil(3 * sigma)), h - 1, w - 1))
    x = torch.arange(-radius, radius + 1, device=images.device, dtype=images.dtype)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    flat = images.reshape(n * c, 1, h, w)
    flat = F.conv2d(F.pad(flat, (radius, radius, 0, 0), mode="reflect"), kernel.view(1, 1, 1, -1))
    flat = F.conv2d(F.pad(flat, (0, 0, radius, radius), mode="reflect"), kernel.view(1, 1, -1, 1))
    return flat.reshape(n, c, h, w)


class PhotometricLoss(nn.Module):
    """λ_mse·MSE + λ_lpips·LPIPS between rendered and real target views, computed in fp32; optionally plus
    ``context_weight`` times the same loss on the context views, and blurred early on (see the module doc).

    forward(pred, target, step, context_pred, context) with pred, target [B, Vt, 3, H, W] and context_pred,
    context [B, Vc, 3, H, W] in [0, 1] (the context pair when ``renders_context``) -> dict of scalar tensors:
    total, mse, lpips (if used), context_mse (and context_lpips) with the context views.
    """

    def __init__(self, cfg: LossConfig, lpips: FrozenLpips | None) -> None:
        super().__init__()
        if cfg.lpips_weight > 0 and lpips is None:
            raise ValueError("lpips_weight > 0 needs the LPIPS network: maybe_lpips(required=True)")
        self.cfg = cfg
        self.lpips = lpips if cfg.lpips_weight > 0 else None

    @property
    def renders_context(self) -> bool:
        """Whether the loss wants the context views rendered too."""
        return self.cfg.context_weight > 0

    def _photometric(self, pred: Tensor, target: Tensor, sigma: float, prefix: str) -> dict[str, Tensor]:
        """Weighted MSE (+ LPIPS) of [B, V, 3, H, W] images after a blur of ``sigma`` px; "total" unprefixed."""
        pred, target = pred.float().flatten(0, 1), target.float().flatten(0, 1)
        pred, target = gaussian_blur(pred, sigma), gaussian_blur(target, sigma)
        terms = {f"{prefix}mse": F.mse_loss(pred, target)}
        total = self.cfg.mse_weight * terms[f"{prefix}mse"]
        if self.lpips is not None:
            terms[f"{prefix}lpips"] = self.lpips(pred, target).mean()
            total = total + self.cfg.lpips_weight * terms[f"{prefix}lpips"]
        return {**terms, "total": total}

    def forward(
        self,
        pred: Tensor,
        target: Tensor,
        step: int = 0,
        context_pred: Tensor | None = None,
        context: Tensor | None = None,
    ) -> dict[str, Tensor]:
        if self.renders_context and (context_pred is None or context is None):
            raise ValueError("model.loss.context_weight > 0: pass the rendered and the real context views")
        sigma = self.cfg.blur_at(step)
        with torch.autocast(pred.device.type, enabled=False):
            terms = self._photometric(pred, target, sigma, "")
            if self.renders_context:
                extra = self._photometric(context_pred, context, sigma, "context_")
                total = terms["total"] + self.cfg.context_weight * extra.pop("total")
                terms = {**terms, **extra, "total": total}
        return terms


def camera_loss(
    pred_extrinsics: Tensor,
    pred_intrinsics: Tensor,
    gt_extrinsics: Tensor,
    gt_intrinsics: Tensor,
    rotation_weight: float = 1.0,
) -> dict[str, Tensor]:
    """Supervised camera loss (``LossConfig.pose_weight``), fp32. All extrinsics [B, V, 4, 4] camera-to-world
    in context view 0's frame (view 0 the identity, as the camera head predicts and ``dataset_cameras``
    gives), intrinsics [B, V, 3, 3] normalised. Terms over views 1..V-1: ``rotation``, the angle between the
    rotations in radians (an L1-like geodesic loss: its gradient does not vanish for the small angles of
    nearby views, as a squared matrix distance's does; finite at zero, see ``rotation_angle_deg``);
    ``translation``, the L1 distance of the translations (the data set's scale: the warm start renders with
    its cameras, so depth learns that scale too); over all views ``focal``, the L1 distance of the normalised
    focal lengths. ``total`` is their sum, the rotation term times ``rotation_weight``."""
    with torch.autocast(pred_extrinsics.device.type, enabled=False):
        pe, ge = pred_extrinsics[:, 1:].float(), gt_extrinsics[:, 1:].float()
        rotation = torch.deg2rad(rotation_angle_deg(pe, ge)).mean()
        translation = (pe[..., :3, 3] - ge[..., :3, 3]).abs().sum(-1).mean()
        focal_of = lambda k: torch.stack([k[..., 0, 0], k[..., 1, 1]], -1).float()  # noqa: E731
        focal = (focal_of(pred_intrinsics) - focal_of(gt_intrinsics)).abs().mean()
    return {"rotation": rotation, "translation": translation, "focal": focal,
            "total": rotation_weight * rotation + translation + focal}  # fmt: skip
