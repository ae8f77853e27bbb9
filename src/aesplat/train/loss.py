"""Photometric loss λ_mse·MSE + λ_lpips·LPIPS(VGG) on target views, and the frozen LPIPS network.

The LPIPS network is torchmetrics' implementation (its linear layers ship inside torchmetrics). Its VGG16
backbone needs torchvision's ImageNet weights, which are read from the local torch hub cache and never
downloaded. The network is held outside the module tree on purpose: it is never trained, never moved by an
optimizer and never written into a checkpoint.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

VGG16_FILE = "vgg16-397923af.pth"  # torchvision's VGG16_Weights.IMAGENET1K_V1


@dataclass
class LossConfig:
    """Loss weights; ``lpips_weight: 0`` opts out of LPIPS (then the VGG weights are optional)."""

    mse_weight: float = 1.0
    lpips_weight: float = 0.05


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


class PhotometricLoss(nn.Module):
    """λ_mse·MSE + λ_lpips·LPIPS between rendered and real target views, computed in fp32.

    forward(pred, target) with [B, V, 3, H, W] in [0, 1] -> dict of scalar tensors: total, mse, lpips (if used).
    """

    def __init__(self, cfg: LossConfig, lpips: FrozenLpips | None) -> None:
        super().__init__()
        if cfg.lpips_weight > 0 and lpips is None:
            raise ValueError("lpips_weight > 0 needs the LPIPS network: maybe_lpips(required=True)")
        self.cfg = cfg
        self.lpips = lpips if cfg.lpips_weight > 0 else None

    def forward(self, pred: Tensor, target: Tensor) -> dict[str, Tensor]:
        with torch.autocast(pred.device.type, enabled=False):
            pred, target = pred.float(), target.float()
            terms = {"mse": F.mse_loss(pred, target)}
            total = self.cfg.mse_weight * terms["mse"]
            if self.lpips is not None:
                terms["lpips"] = self.lpips(pred.flatten(0, 1), target.flatten(0, 1)).mean()
                total = total + self.cfg.lpips_weight * terms["lpips"]
        terms["total"] = total
        return terms
