"""The AESplat network: patch encoder, masked geometry transformer, camera / depth / Gaussian heads and the
decoupled appearance (I2DC, GVSRE, WCM, view-dependent head). Plain ``nn.Module``s, no Lightning."""

from .appearance import (
    APPEARANCE_MODES,
    GVSRE,
    DecoupledAppearance,
    ViewDependentHead,
    gvsre_descriptor,
    i2dc,
    warped_color_map,
)
from .camera_head import CameraHead
from .dpt import DPT, DepthHead
from .encoder import EncoderConfig, PatchEncoder
from .gaussian_head import GaussianHead, GaussianHeadOutput
from .model import SIZES, AESplatModel, ModelConfig, ModelOutput, NetConfig, build_model
from .transformer import GeometryTransformer, TransformerConfig
from .weights import (
    WeightsReport,
    convert_encoder_state_dict,
    load_encoder_weights,
    load_pretrained_weights,
    load_vggt_weights,
)

__all__ = [
    "APPEARANCE_MODES",
    "DPT",
    "GVSRE",
    "SIZES",
    "AESplatModel",
    "CameraHead",
    "DecoupledAppearance",
    "DepthHead",
    "EncoderConfig",
    "GaussianHead",
    "GaussianHeadOutput",
    "GeometryTransformer",
    "ModelConfig",
    "ModelOutput",
    "NetConfig",
    "PatchEncoder",
    "TransformerConfig",
    "ViewDependentHead",
    "WeightsReport",
    "build_model",
    "convert_encoder_state_dict",
    "gvsre_descriptor",
    "i2dc",
    "load_encoder_weights",
    "load_pretrained_weights",
    "load_vggt_weights",
    "warped_color_map",
]
