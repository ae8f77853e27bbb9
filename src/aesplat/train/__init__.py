"""Training and evaluation: LightningModule, loss, optimizer groups, metrics, callbacks, evaluation outputs."""

from .evaluation import EvalConfig
from .loss import LossConfig, LpipsWeightsMissing, PhotometricLoss, load_lpips_network, vgg16_weights_path
from .module import AESplatModule, NetConfig
from .optim import OptimConfig, WarmupCosine, build_optimizer, build_param_groups

__all__ = [
    "AESplatModule",
    "EvalConfig",
    "LossConfig",
    "LpipsWeightsMissing",
    "NetConfig",
    "OptimConfig",
    "PhotometricLoss",
    "WarmupCosine",
    "build_optimizer",
    "build_param_groups",
    "load_lpips_network",
    "vgg16_weights_path",
]
