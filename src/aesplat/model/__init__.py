"""The AESplat network: patch encoder, masked geometry transformer, camera / depth / Gaussian heads and the
decoupled appearance (I2DC, GVSRE, WCM, view-dependent head). Plain ``nn.Module``s, no Lightning."""

from .appearance import (
    APPEARANCE_MODES,
    VIEW_AGGREGATIONS,
    ConcatAppearance,
    DecoupledAppearance,
    PooledAppearance,
    ShallowMLP,
    ViewDependentHead,
    build_appearance,
    gvsre_descriptor,
    i2dc,
    masked_mean,
    warped_color_map,
)
from .camera_head import CameraHead
from .dpt import DPT, DepthHead
from .encoder import EncoderConfig, PatchEncoder
from .gaussian_head import GaussianHead, GaussianHeadOutput
from .model import (
    CAMERA_SOURCES,
    SIZES,
    AESplatModel,
    CameraSource,
    ModelConfig,
    ModelOutput,
    NetConfig,
    NetOptions,
    build_model,
    checkpoint_cameras,
    dataset_cameras,
    forward_batch,
)
from .transformer import GeometryTransformer, TransformerConfig
from .weights import (
    WeightsReport,
    convert_encoder_state_dict,
    load_encoder_weights,
    load_pretrained_weights,
    load_vggt_weights,
    load_weights,
)

__all__ = [
    "APPEARANCE_MODES",
    "CAMERA_SOURCES",
    "DPT",
    "SIZES",
    "VIEW_AGGREGATIONS",
    "AESplatModel",
    "CameraHead",
    "CameraSource",
    "ConcatAppearance",
    "DecoupledAppearance",
    "DepthHead",
    "EncoderConfig",
    "GaussianHead",
    "GaussianHeadOutput",
    "GeometryTransformer",
    "ModelConfig",
    "ModelOutput",
    "NetConfig",
    "NetOptions",
    "PatchEncoder",
    "PooledAppearance",
    "ShallowMLP",
    "TransformerConfig",
    "ViewDependentHead",
    "WeightsReport",
    "build_appearance",
    "build_model",
    "checkpoint_cameras",
    "convert_encoder_state_dict",
    "dataset_cameras",
    "forward_batch",
    "gvsre_descriptor",
    "i2dc",
    "load_encoder_weights",
    "load_pretrained_weights",
    "load_vggt_weights",
    "load_weights",
    "masked_mean",
    "warped_color_map",
]
