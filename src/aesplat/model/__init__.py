"""The AESplat network: patch encoder, masked geometry transformer, camera / depth / Gaussian heads and the
decoupled appearance (I2DC, GVSRE, WCM, view-dependent head). Plain ``nn.Module``s, no Lightning."""

from .appearance import (
    APPEARANCE_MODES,
    ConcatAppearance,
    PooledAppearance,
    ViewDependentHead,
    build_appearance,
    gvsre_descriptor,
    i2dc,
    masked_mean,
    warped_color_map,
)
from .encoder import EncoderConfig, PatchEncoder
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
from .transformer import TransformerConfig
from .weights import convert_encoder_state_dict, load_encoder_weights

__all__ = [
    "APPEARANCE_MODES",
    "CAMERA_SOURCES",
    "SIZES",
    "AESplatModel",
    "CameraSource",
    "ConcatAppearance",
    "EncoderConfig",
    "ModelConfig",
    "ModelOutput",
    "NetConfig",
    "NetOptions",
    "PatchEncoder",
    "PooledAppearance",
    "TransformerConfig",
    "ViewDependentHead",
    "build_appearance",
    "build_model",
    "checkpoint_cameras",
    "convert_encoder_state_dict",
    "dataset_cameras",
    "forward_batch",
    "gvsre_descriptor",
    "i2dc",
    "load_encoder_weights",
    "masked_mean",
    "warped_color_map",
]
