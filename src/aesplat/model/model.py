"""The assembled AESplat model: NAS3R's network (VGGT's aggregator: a DINOv2 patch encoder and alternating
attention; VGGT's camera and depth heads; NAS3R's Gaussian head) -> decoupled appearance -> Gaussians in view
0's frame plus a camera for every input view. Every size is the same modules at other widths; ``large`` is
NAS3R's network exactly, and its checkpoints load by name (``nas3r.py``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, get_args

import torch
from torch import Tensor, nn

from aesplat.errors import UserError
from aesplat.geometry import relative_to_first, unproject_depth
from aesplat.types import BatchedExample, Gaussians

from .appearance import VIEW_AGGREGATIONS, appearance_mode, build_appearance
from .camera_head import CameraHead
from .dpt import DepthHead
from .encoder import EncoderConfig, PatchEncoder
from .gaussian_head import GaussianHead, pixel_scales_to_scene
from .transformer import Aggregator, TransformerConfig
from .weights import WeightsReport, load_weights

log = logging.getLogger(__name__)

# parameter-name prefix -> optimizer group; the rest is "rest"
_GROUP_OF = {"appearance.": "appearance", "aggregator.patch_embed.": "backbone"}
COMPILE_MODES = ("none", "blocks")

# Where a run's cameras come from (``model.cameras``): the camera head (the method: pose-free), or the data
# set's poses and intrinsics (posed training; the appearance model measured without the pose head).
CameraSource = Literal["predicted", "dataset"]
CAMERA_SOURCES: tuple[str, ...] = get_args(CameraSource)


@dataclass(frozen=True)
class ModelConfig:
    """Everything that defines the network. ``build_model`` fills it from a size preset plus overrides."""

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    head_features: int = 128  # DPT fusion width
    head_channels: tuple[int, int, int, int] = (96, 192, 384, 384)  # DPT reassemble widths, fine to coarse
    head_precision: str = "fp32"  # fp32 | bf16: the DPT trunks' convolutions under bf16 autocast
    camera_depth: int = 4  # transformer blocks of the camera head (VGGT: 4, at twice the trunk's width)
    camera_iterations: int = 1  # refinements of the pose encoding (NAS3R: 1; VGGT: 4)
    camera_correlation: bool = False  # the camera head also sees a view-0 cost volume (ViewCorrelation)
    # The camera head's attention across views masked as the trunk's global attention (context cameras never
    # see the targets); False: NAS3R's head, where the target images change the context cameras.
    camera_mask: bool = True
    # Where in its pixel each pixel's Gaussian is unprojected: 0.0 the top-left corner (u / W, v / H), NAS3R's;
    # 0.5 the centre, where the renderer samples that pixel (with 0.0 each I2DC colour is drawn half a pixel
    # off; on the demo's validation scenes 0.5 scored lower: docs/nas3r.md)
    pixel_offset: float = 0.0
    appearance: str = "full"
    sh_degree: int = 4
    # How the view-dependent head takes in the other context views: concat (the paper's; its width fixes the
    # number of context views to num_context_views) or pool (any number); see appearance.py.
    view_aggregation: str = "concat"
    num_context_views: int = 2  # the count a concat head is built for (pool takes any)
    gvsre_dim: int = 32
    appearance_hidden: int = 128
    # The depth head's range (z-depth, scene units): the one place a run's depth range lives (model.net.near /
    # model.net.far set it); the data carry none. depth = near + (far - near)·sigmoid: NAS3R's, with 1 and 100.
    near: float = 1.0
    far: float = 100.0
    # What the Gaussian head's scales mean (gaussian_head.SCALE_MODES): absolute (scene units, NAS3R's:
    # scale_multiplier * softplus) or pixel (scale_pixels: pixels at the Gaussian's own depth); both capped at
    # scale_max scene units.
    scale_mode: str = "absolute"
    scale_multiplier: float = 0.001
    scale_pixels: tuple[float, float] = (0.5, 15.0)
    scale_max: float = 0.3
    weights: str | None = None  # local DINOv2, VGGT, NAS3R or aesplat checkpoint (see weights.py)


SIZES: dict[str, ModelConfig] = {
    # CPU tests and the CPU demo: the same modules at width 96, 4 + 4 blocks, a 2-block camera head.
    "tiny": ModelConfig(
        encoder=EncoderConfig(dim=96, depth=4, num_heads=3, pos_grid=16),
        transformer=TransformerConfig(dim=96, depth=4, num_heads=3, num_register_tokens=2),
        head_features=32,
        head_channels=(24, 48, 96, 96),
        camera_depth=2,
        gvsre_dim=16,
        appearance_hidden=32,
    ),
    # DINOv2 ViT-B/14 encoder (4 registers), 12 + 12 alternating blocks of width 768.
    "base": ModelConfig(
        encoder=EncoderConfig(dim=768, depth=12, num_heads=12, num_registers=4),
        transformer=TransformerConfig(dim=768, depth=12, num_heads=12),
        head_features=128,
        head_channels=(96, 192, 384, 768),
    ),
    # NAS3R's network (VGGT-1B's aggregator and heads): DINOv2 ViT-L/14 with 4 registers, 24 frame + 24 global
    # blocks of width 1024, DPT width 256, SH degree 4 (83 Gaussian channels).
    "large": ModelConfig(
        encoder=EncoderConfig(dim=1024, depth=24, num_heads=16, num_registers=4),
        transformer=TransformerConfig(dim=1024, depth=24, num_heads=16, layers=(4, 11, 17, 23)),
        head_features=256,
        head_channels=(256, 512, 1024, 1024),
    ),
}

# build_model keyword -> (sub-config, field); every other keyword is a ModelConfig field.
_NESTED = {
    "rope": ("transformer", "rope"),
    "num_register_tokens": ("transformer", "num_register_tokens"),
    "qk_norm": ("transformer", "qk_norm"),
    "encoder_registers": ("encoder", "num_registers"),
    "patch_size": ("encoder", "patch_size"),
    "intrinsics_tokens": ("transformer", "intrinsics_tokens"),
}


@dataclass(frozen=True)
class ModelOutput:
    """One forward pass.

    gaussians   Gaussians, one per context pixel in (view, row, column) order, in view 0's frame:
                means [B, N, 3], quats [B, N, 4], scales [B, N, 3], opacities [B, N], sh [B, N, K, 3],
                N = Vc·H·W, K = (L + 1)^2
    extrinsics  [B, Vc + Vt, 4, 4] camera-to-world in view 0's frame (view 0 is the identity), context first
    intrinsics  [B, Vc + Vt, 3, 3] normalised
    depth       [B, Vc, H, W] predicted z-depth of the context views
    depth_confidence  [B, Vc, H, W] the depth head's confidence (> 1)
    predicted_cameras  (extrinsics, intrinsics) of the camera head, as above, when the cameras above were
                given (``forward(..., extrinsics=E, intrinsics=K)``) and target images too, so that the
                head's predictions can be supervised (a posed warm start); else None
    """

    gaussians: Gaussians
    extrinsics: Tensor
    intrinsics: Tensor
    depth: Tensor
    predicted_cameras: tuple[Tensor, Tensor] | None = None
    depth_confidence: Tensor | None = None

    @property
    def num_context_views(self) -> int:
        return self.depth.shape[1]


class AESplatModel(nn.Module):
    """Pose-free feed-forward Gaussian splatting with decoupled appearance (docs/design.md).

    forward(context_images [B, Vc, 3, H, W], target_images [B, Vt, 3, H, W] | None) -> ModelOutput, images
    float in [0, 1], H and W multiples of the patch size (14 unless ``patch_size`` is set), Vc >= 2. The
    encoder and the geometry transformer follow any surrounding autocast; the heads, geometry and appearance
    run in float32 (with ``head_precision="bf16"`` the DPT trunks' convolutions run in bf16, their outputs and
    all that follows in float32).

    forward(context_images, extrinsics=E, intrinsics=K) uses the cameras E [B, V, 4, 4] (camera-to-world in
    context view 0's frame) and K [B, V, 3, 3] (normalised) instead of the camera head's, which does not run;
    V >= Vc, the first Vc are the context cameras and the rest are passed through as the target cameras.
    Target images are then not needed (they only ever serve to predict the target cameras); given as well,
    the camera head runs on all views and its cameras come back in ``ModelOutput.predicted_cameras`` (for a
    supervised pose loss) while the Gaussians and renders use the given ones.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        t = cfg.transformer
        patch = cfg.encoder.patch_size
        self.aggregator = Aggregator(cfg.encoder, t)
        token_dim = 2 * t.dim
        self.camera_head = CameraHead(
            token_dim, t.num_heads, cfg.camera_depth, cfg.camera_iterations, cfg.camera_correlation
        )
        self.depth_head = DepthHead(
            token_dim, cfg.head_features, cfg.head_channels, patch, cfg.near, cfg.far, cfg.head_precision
        )
        self.appearance = build_appearance(
            cfg.view_aggregation, cfg.appearance, cfg.sh_degree, cfg.head_features // 2,
            cfg.num_context_views, cfg.gvsre_dim, cfg.appearance_hidden,
        )  # fmt: skip
        self.gaussian_head = GaussianHead(
            token_dim, cfg.head_features, cfg.head_channels, patch, cfg.sh_degree, cfg.scale_multiplier,
            cfg.scale_max, cfg.head_precision, cfg.scale_mode, cfg.scale_pixels,
        )  # fmt: skip
        self.weights_report: WeightsReport | None = None
        if cfg.weights:
            self.weights_report = load_weights(self, cfg.weights)
            log.info("loaded %d tensors from %s", len(self.weights_report.loaded), self.weights_report.path)

    @property
    def encoder(self) -> PatchEncoder:
        """The DINOv2 patch encoder (``aggregator.patch_embed``)."""
        return self.aggregator.patch_embed

    @property
    def takes_intrinsics(self) -> bool:
        """Whether the network reads every view's intrinsics (NAS3R's ``-I``): they must then be given."""
        return self.cfg.transformer.intrinsics_tokens

    @property
    def sh_degree(self) -> int:
        """SH degree of the predicted Gaussians (0 where the appearance mode has no higher orders)."""
        return self.appearance.sh_degree

    @property
    def patch_size(self) -> int:
        """Pixels per patch side: image sides must be multiples of it."""
        return self.cfg.encoder.patch_size

    def check_context_views(self, count: int) -> None:
        """Refuse, with one line (UserError), a number of context views this network cannot take."""
        if count < 2:
            raise UserError(f"the model needs at least 2 context views, got {count}")
        self.appearance.check_context_views(count)

    @property
    def pretrained_backbone(self) -> bool:
        """Whether pretrained encoder weights were loaded (training gives them a lower learning rate)."""
        report = self.weights_report
        if report is None:
            return False
        return any(k.startswith("aggregator.patch_embed.") for k in report.loaded)

    def transformer_blocks(self) -> list[nn.Module]:
        """Every encoder, frame and global block: the units that ``compile_blocks`` compiles."""
        t = self.aggregator
        return [*t.patch_embed.blocks, *t.frame_blocks, *t.global_blocks]

    def compile_blocks(self, **options: Any) -> None:
        """Compile each encoder and transformer block in place (``nn.Module.compile``): regional compilation.

        Blocks of one kind share their code, so torch compiles each kind once (plus once per new input shape)
        instead of the whole network; the rest stays eager. In place, so parameter names and ``state_dict``
        keys do not change (no ``_orig_mod.`` prefix). ``options`` go to ``torch.compile``.
        """
        for block in self.transformer_blocks():
            block.compile(**options)

    def named_parameter_groups(self) -> dict[str, list[tuple[str, nn.Parameter]]]:
        """Trainable parameters by optimizer group: ``appearance`` (view-dependent head + GVSRE MLP),
        ``backbone`` (the patch encoder) and ``rest``. Every trainable parameter is in exactly one group."""
        groups: dict[str, list[tuple[str, nn.Parameter]]] = {"appearance": [], "backbone": [], "rest": []}
        for name, param in self.named_parameters():
            if not param.requires_grad:
                continue
            group = next((g for prefix, g in _GROUP_OF.items() if name.startswith(prefix)), "rest")
            groups[group].append((name, param))
        return groups

    def _check_cameras(
        self, context: Tensor, views: int, extrinsics: Tensor | None, intrinsics: Tensor | None
    ) -> None:
        """Given cameras, for the ``views`` views of a forward pass (context and target images)."""
        b, vc = context.shape[:2]
        if self.takes_intrinsics and intrinsics is not None:
            if intrinsics.ndim != 4 or intrinsics.shape[0] != b or intrinsics.shape[2:] != (3, 3):
                raise ValueError(f"intrinsics must be [B, V, 3, 3] with B = {b}, got {tuple(intrinsics.shape)}")
            if intrinsics.shape[1] < views:
                raise ValueError(
                    f"this network takes the intrinsics of all {views} views, got {intrinsics.shape[1]}"
                )
            if extrinsics is None:
                return
        if (extrinsics is None) != (intrinsics is None):
            raise ValueError("give both extrinsics and intrinsics to replace the camera head's, or neither")
        if extrinsics is None:
            if self.takes_intrinsics:
                raise UserError("this network (NAS3R -I) takes every view's intrinsics: give them")
            return
        v = extrinsics.shape[1] if extrinsics.ndim == 4 else -1
        if extrinsics.shape != (b, v, 4, 4) or intrinsics.shape != (b, v, 3, 3) or v < vc:
            raise ValueError(
                f"given cameras must be extrinsics [B, V, 4, 4] and intrinsics [B, V, 3, 3] with B = {b} and "
                f"V >= {vc} context views, got {tuple(extrinsics.shape)} and {tuple(intrinsics.shape)}"
            )

    def _check_inputs(self, context: Tensor, target: Tensor | None) -> None:
        if context.ndim != 5 or context.shape[2] != 3:
            raise ValueError(f"context_images must be [B, Vc, 3, H, W], got shape {tuple(context.shape)}")
        if not context.is_floating_point():
            raise TypeError(f"context_images must be float in [0, 1], got {context.dtype}; divide uint8 by 255")
        b, vc, _, h, w = context.shape
        self.check_context_views(vc)
        p = self.patch_size
        if h % p or w % p:
            raise ValueError(f"image height and width must be multiples of the patch size {p}, got {h}x{w}")
        if target is not None:
            if target.ndim != 5 or target.shape[0] != b or target.shape[2:] != context.shape[2:]:
                raise ValueError(
                    f"target_images must be [B, Vt, 3, H, W] matching the context {tuple(context.shape)}, "
                    f"got {tuple(target.shape)}"
                )

    def forward(
        self,
        context_images: Tensor,
        target_images: Tensor | None = None,
        extrinsics: Tensor | None = None,
        intrinsics: Tensor | None = None,
    ) -> ModelOutput:
        self._check_inputs(context_images, target_images)
        b, vc, _, h, w = context_images.shape
        views = vc + (0 if target_images is None else target_images.shape[1])
        self._check_cameras(context_images, views, extrinsics, intrinsics)
        if extrinsics is not None and target_images is not None and extrinsics.shape[1] != views:
            raise ValueError(
                f"with target images, give cameras for all {views} views, got {extrinsics.shape[1]}"
            )
        images = context_images if target_images is None else torch.cat([context_images, target_images], dim=1)
        # NAS3R -I: the network reads every view's intrinsics and keeps them; its head predicts the poses
        known_k = intrinsics[:, :views] if self.takes_intrinsics else None
        layers = self.aggregator(images, vc, known_k)

        with torch.autocast(device_type=images.device.type, enabled=False):
            layers = [x.float() for x in layers]
            context_images = context_images.float()

            def head_cameras() -> tuple[Tensor, Tensor]:
                e, k = self.camera_head(
                    layers[-1][:, :, 0], images, w / h, vc if self.cfg.camera_mask else None
                )
                return e, (k if known_k is None else known_k.float())

            predicted = None
            if extrinsics is None:
                extrinsics, intrinsics = head_cameras()
            elif target_images is not None:  # given cameras render; the head's are only supervised
                predicted = head_cameras()
            extrinsics, intrinsics = extrinsics.float(), intrinsics.float()
            start = self.aggregator.patch_start
            context_tokens = [x[:, :vc, start:].flatten(0, 1) for x in layers]  # 4 x [B·Vc, P, 2·dim]

            depth, confidence = self.depth_head(context_tokens, (h, w))
            depth, confidence = depth.unflatten(0, (b, vc)), confidence.unflatten(0, (b, vc))  # [B, Vc, H, W]
            ctx_k, ctx_e = intrinsics[:, :vc], extrinsics[:, :vc]
            # NAS3R unprojects pixel (u, v) through (u / W, v / H), its top-left corner: pixel_offset 0
            means = unproject_depth(depth, ctx_k, ctx_e, offset=self.cfg.pixel_offset).reshape(b, vc, h * w, 3)

            g = self.gaussian_head(context_tokens, context_images.flatten(0, 1))
            scales = g.scales.unflatten(0, (b, vc))  # [B, Vc, P, 3]
            if self.cfg.scale_mode == "pixel":
                scales = pixel_scales_to_scene(scales, depth, ctx_k, self.cfg.scale_max)
            features, head_sh = g.features.unflatten(0, (b, vc)), g.sh.unflatten(0, (b, vc))
            sh = self.appearance(context_images, means, features, head_sh, ctx_k, ctx_e)  # [B, N, K, 3]
            gaussians = Gaussians(
                means=means.reshape(b, -1, 3),
                quats=g.quats.reshape(b, -1, 4),
                scales=scales.reshape(b, -1, 3),
                opacities=g.opacities.reshape(b, -1),
                sh=sh,
            )
        return ModelOutput(gaussians=gaussians, extrinsics=extrinsics, intrinsics=intrinsics, depth=depth,
                           predicted_cameras=predicted, depth_confidence=confidence)  # fmt: skip


def checkpoint_cameras(checkpoint: dict) -> str:
    """The camera source a training checkpoint (the loaded dict) was trained with; older ones: predicted."""
    return (checkpoint.get("hyper_parameters") or {}).get("cameras", "predicted")


def forward_batch(
    model: AESplatModel, batch: BatchedExample, cameras: str = "predicted", predict_cameras: bool = False
) -> ModelOutput:
    """``model`` on the views of ``batch`` with its cameras from ``cameras`` (one of ``CAMERA_SOURCES``).

    predicted: the camera head predicts every view's camera from the context and target images (a network
    that reads intrinsics, NAS3R's -I, is given the batch's and predicts the poses).
    dataset: the batch's own cameras, every view's pose expressed relative to context view 0; the model
    sees the context images only, or, with ``predict_cameras``, all images, and its camera head's
    predictions come back in ``predicted_cameras`` (a supervised pose loss: the posed warm start).
    """
    if cameras == "predicted":
        if model.takes_intrinsics:  # NAS3R -I: the data set's intrinsics go in, the poses are predicted
            k = torch.cat([batch.context.intrinsics, batch.target.intrinsics], dim=1).float()
            return model(batch.context.images, batch.target.images, intrinsics=k)
        return model(batch.context.images, batch.target.images)
    if cameras == "dataset":
        extrinsics, intrinsics = dataset_cameras(batch)
        target = batch.target.images if predict_cameras else None
        return model(batch.context.images, target, extrinsics=extrinsics, intrinsics=intrinsics)
    raise ValueError(f"unknown camera source {cameras!r}; choose one of {', '.join(CAMERA_SOURCES)}")


def dataset_cameras(batch: BatchedExample) -> tuple[Tensor, Tensor]:
    """The batch's cameras, context views first: extrinsics [B, Vc + Vt, 4, 4] camera-to-world in context
    view 0's frame (view 0 the identity), intrinsics [B, Vc + Vt, 3, 3] normalised; float32."""
    extrinsics = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1).double()
    intrinsics = torch.cat([batch.context.intrinsics, batch.target.intrinsics], dim=1).float()
    return relative_to_first(extrinsics).float(), intrinsics  # float64 first: world poses can be far away


def build_model(size: str = "tiny", appearance: str = "full", sh_degree: int = 4, **kwargs) -> AESplatModel:
    """Build an AESplat model from a size preset (``tiny``, ``base``, ``large``) and overrides.

    appearance: a key of ``APPEARANCE_MODES`` (the paper's ablation rows).
    kwargs: any :class:`ModelConfig` field (``near``, ``far``, ``weights``, ``view_aggregation``,
    ``num_context_views``, ...) and ``rope``, ``num_register_tokens``, ``qk_norm`` (geometry transformer),
    ``encoder_registers``, ``patch_size`` (encoder; 14 is DINOv2's and the only one pretrained weights fit).
    """
    if size not in SIZES:
        raise ValueError(f"unknown model size {size!r}; choose one of {', '.join(SIZES)}")
    higher = appearance_mode(appearance).higher
    cfg = replace(SIZES[size], appearance=appearance, sh_degree=sh_degree)
    top = {f.name for f in fields(ModelConfig)} - {"encoder", "transformer"}
    nested: dict[str, dict] = {"encoder": {}, "transformer": {}}
    direct = {}
    for key, value in kwargs.items():
        if key in _NESTED:
            part, name = _NESTED[key]
            nested[part][name] = value
        elif key in top:
            direct[key] = value
        else:
            allowed = ", ".join(sorted(top | set(_NESTED)))
            raise TypeError(f"build_model got an unknown option {key!r}; options are: {allowed}")
    for key in ("head_channels", "scale_pixels"):
        if direct.get(key) is not None:
            direct[key] = tuple(direct[key])
    cfg = replace(
        cfg,
        encoder=replace(cfg.encoder, **nested["encoder"]),
        transformer=replace(cfg.transformer, **nested["transformer"]),
        **direct,
    )
    if higher == "none" and cfg.sh_degree != 0:
        log.info("appearance=%s uses SH degree 0 (requested %d)", cfg.appearance, cfg.sh_degree)
    return AESplatModel(cfg)


@dataclass
class NetOptions:
    """The ``model.net.options`` section: the other :func:`build_model` keywords, each typed. None (the default)
    keeps the size preset's value; only the values given reach ``build_model``."""

    camera_correlation: bool | None = None  # the camera head also sees a view-0 cost volume
    num_context_views: int | None = None  # the count a concat appearance head is built for (pool takes any)
    patch_size: int | None = None  # encoder patch side; 14 is DINOv2's and the only one pretrained weights fit
    encoder_registers: int | None = None  # encoder register tokens (DINOv2 "reg4" and VGGT: 4)
    num_register_tokens: int | None = None  # geometry transformer register tokens (VGGT: 4)
    rope: bool | None = None  # 2D rotary position embedding in the geometry transformer
    qk_norm: bool | None = None  # normalised queries and keys in the geometry transformer
    head_precision: str | None = None  # fp32 | bf16: the DPT trunks' convolutions under bf16 autocast
    head_features: int | None = None  # DPT fusion width
    head_channels: tuple[int, int, int, int] | None = None  # DPT reassemble widths, fine to coarse
    camera_depth: int | None = None  # transformer blocks of the camera head (VGGT: 4)
    camera_iterations: int | None = None  # refinements of the pose encoding (NAS3R: 1)
    camera_mask: bool | None = None  # false: NAS3R's camera head, whose context cameras see the target views
    pixel_offset: float | None = None  # 0.0: Gaussians through pixel corners (NAS3R's); 0.5: through centres
    intrinsics_tokens: bool | None = None  # NAS3R -I: the network reads every view's intrinsics
    gvsre_dim: int | None = None  # GVSRE output width
    appearance_hidden: int | None = None  # view-dependent head MLP width
    scale_mode: str | None = None  # absolute (scene units, the paper's) | pixel (pixels at its depth)
    scale_multiplier: float | None = None  # absolute mode: Gaussian scale = multiplier * softplus(.)
    scale_pixels: tuple[float, float] | None = None  # pixel mode: the range of scales, in pixels
    scale_max: float | None = None  # cap of the Gaussian scales (scene units)

    def given(self) -> dict[str, Any]:
        """The options set (not None), as :func:`build_model` keywords."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


@dataclass
class NetConfig:
    """A run's network settings: the arguments of :func:`build_model` (the ``model.net`` config section)."""

    size: str = "tiny"
    appearance: str = "full"  # full | no_gvsre | no_wcm | i2dc_only | baseline | baseline_i2dc
    # concat: the paper's appearance head, built for options.num_context_views (2); pool: any number of views
    view_aggregation: str = "concat"
    sh_degree: int = 4
    near: float = ModelConfig.near  # the depth head's range: depth = near + (far - near)·sigmoid(·)
    far: float = ModelConfig.far
    weights: str | None = None  # local DINOv2/timm, VGGT or aesplat training checkpoint file; never downloaded
    options: NetOptions = field(default_factory=NetOptions)  # the other build_model keywords (rope, ...)
    compile: str = "none"  # none | blocks: torch.compile each encoder / transformer block (first steps slower)

    def __post_init__(self) -> None:
        if self.compile not in COMPILE_MODES:
            choices = ", ".join(COMPILE_MODES)
            raise ValueError(f"unknown model.net.compile {self.compile!r}; choose one of {choices}")
        if self.view_aggregation not in VIEW_AGGREGATIONS:
            choices = ", ".join(VIEW_AGGREGATIONS)
            raise ValueError(
                f"unknown model.net.view_aggregation {self.view_aggregation!r}; choose one of {choices}"
            )
        if isinstance(self.options, dict):  # as checkpoints store it
            known = sorted(f.name for f in fields(NetOptions))
            if unknown := sorted(set(self.options) - set(known)):
                raise ValueError(f"model.net.options: unknown key(s) {unknown}; known: {known}")
            self.options = NetOptions(**self.options)
        elif self.options is None:
            self.options = NetOptions()

    def build(self) -> AESplatModel:
        model = build_model(size=self.size, appearance=self.appearance, sh_degree=self.sh_degree,
                            view_aggregation=self.view_aggregation, near=self.near, far=self.far,
                            weights=self.weights, **self.options.given())  # fmt: skip
        if self.compile == "blocks":
            model.compile_blocks()
        return model

    def random_backbone_warning(self) -> str | None:
        """What `aesplat fit` says when a paper-scale network (base, large) has no weights to start from."""
        if self.size not in ("base", "large") or self.weights:
            return None
        lines = [
            f"The `{self.size}` network starts from a RANDOM backbone: model.net.weights is not set.",
            "The paper builds on VGGT (a pretrained DINOv2 encoder and geometry transformer). From a random",
            "backbone, pose-free training measured no pose learning in 600 steps (conf/re10k.yaml, one H100).",
            "Give a local checkpoint: one of NAS3R's trained networks (docs/nas3r.md), VGGT-1B",
            "(facebook/VGGT-1B) or DINOv2 (facebookresearch/dinov2): --model.net.weights /path/to/vggt_1B.pt",
            "docs/training.md, 'Pretrained weights', says where they come from and which formats load.",
        ]
        rule = "=" * 100
        return "\n".join(["", rule, *lines, rule])
