"""NAS3R's trained networks (github.com/ranrhuang/NAS3R): recognising its Lightning checkpoints, loading them.

NAS3R keeps its network under ``encoder.``: VGGT-1B's layout under ``encoder.backbone.model.`` (the aggregator,
the camera head, the depth head and an unused point head) and its Gaussian head as
``encoder.gaussian_param_head.``. This project's ``large`` network has the same modules under the same names
(``aggregator.``, ``camera_head.``, ``depth_head.``, ``gaussian_head.``), so a checkpoint loads by dropping
the prefixes. Its five VGGT-type checkpoints differ only in their weights, except ``-I``, which adds
``intrinsic_encoder`` (a token from each view's intrinsics). NAS3R-M's (a MASt3R/CroCo trunk) are refused.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from torch import Tensor, nn

from ..errors import UserError

TRUNK = "encoder.backbone.model."
GAUSSIAN_HEAD = "encoder.gaussian_param_head."
# NAS3R's prefix -> this project's, for the modules the two share
RENAMES = {
    TRUNK + "aggregator.": "aggregator.",
    TRUNK + "camera_head.": "camera_head.",
    TRUNK + "depth_head.": "depth_head.",
    GAUSSIAN_HEAD: "gaussian_head.",
}
UNUSED = (TRUNK + "point_head.",)  # VGGT's point head: built by NAS3R, never used
INTRINSICS_KEY = TRUNK + "aggregator.intrinsic_encoder.weight"


@dataclass(frozen=True)
class Nas3rVariant:
    """What a NAS3R checkpoint holds: ``intrinsics`` for the ``-I`` networks (they read every view's
    intrinsics and do not predict them); ``sh_degree`` from its Gaussian head's width."""

    intrinsics: bool
    sh_degree: int

    @property
    def name(self) -> str:
        return "NAS3R-I (takes intrinsics)" if self.intrinsics else "NAS3R"


def is_nas3r_state(state: dict[str, Tensor]) -> bool:
    """Whether a state dict is one of NAS3R's (any network: VGGT-type or NAS3R-M)."""
    return any(k.startswith("encoder.") for k in state) and any(
        k.startswith(("encoder.backbone.", GAUSSIAN_HEAD)) for k in state
    )


def nas3r_variant(state: dict[str, Tensor], path: str | Path) -> Nas3rVariant:
    """The variant of a NAS3R state dict; UserError (one line) for NAS3R-M or a state that lacks the network."""
    if not any(k.startswith(TRUNK + "aggregator.") for k in state):
        raise UserError(
            f"{path} is a NAS3R-M checkpoint (a MASt3R/CroCo trunk, 256x256) or not a whole NAS3R network: "
            "only the VGGT-type NAS3R checkpoints (re10k_nas3r*, 224x224) load into the `large` network"
        )
    out = state.get(GAUSSIAN_HEAD + "scratch.output_conv2.2.weight")
    if out is None:
        raise UserError(f"{path} is a NAS3R checkpoint without its Gaussian head ({GAUSSIAN_HEAD}*)")
    channels = out.shape[0] - 8  # opacity, 3 scales, 4 quaternion
    degree = round((channels / 3) ** 0.5) - 1
    if channels % 3 or (degree + 1) ** 2 * 3 != channels:
        raise UserError(f"{path}: NAS3R's Gaussian head has {out.shape[0]} channels, not 8 + 3·(L+1)²")
    return Nas3rVariant(intrinsics=INTRINSICS_KEY in state, sh_degree=degree)


def convert_nas3r_state(state: dict[str, Tensor]) -> tuple[dict[str, Tensor], list[str]]:
    """NAS3R's tensors under this project's names, and the keys left out (the point head, the rest of the
    Lightning module)."""
    out: dict[str, Tensor] = {}
    ignored: list[str] = []
    for key, value in state.items():
        prefix = next((p for p in RENAMES if key.startswith(p)), None)
        if prefix is None:
            ignored.append(key)
            continue
        out[RENAMES[prefix] + key[len(prefix) :]] = value
    return out, ignored


def nas3r_net(variant: Nas3rVariant) -> dict:
    """The ``model.net`` settings of the network a NAS3R checkpoint is: ``large``, NAS3R's own SH
    (``baseline``), its depth range 1-100, its camera head unmasked (its context cameras see the target views,
    as in NAS3R's own evaluation), Gaussians through pixel corners, intrinsics tokens for ``-I``."""
    return {
        "size": "large",
        "appearance": "baseline",
        "view_aggregation": "pool",
        "sh_degree": variant.sh_degree,
        "near": 1.0,
        "far": 100.0,
        "options": {"intrinsics_tokens": variant.intrinsics, "camera_mask": False, "pixel_offset": 0.0},
    }


def load_nas3r_state(model: nn.Module, state: dict[str, Tensor], path: str | Path):
    """A NAS3R state dict into ``model`` (an AESplatModel of the ``large`` size): every tensor NAS3R has,
    by name. The appearance head, which NAS3R does not have, keeps its initialisation (fine-tuning AESplat's
    appearance on NAS3R's trunk). A shape mismatch, or a ``-I`` checkpoint for a network without intrinsics
    tokens (or the other way round), is one line."""
    from .weights import WeightsReport, _load_matching, _warn

    variant = nas3r_variant(state, path)
    takes = bool(getattr(model, "takes_intrinsics", False))
    if variant.intrinsics != takes:
        fix = "true" if variant.intrinsics else "false"
        raise UserError(
            f"{path} is a {variant.name} checkpoint; set model.net.options.intrinsics_tokens: {fix} to load it"
        )
    converted, ignored = convert_nas3r_state(state)
    report = WeightsReport(path=str(path), format="nas3r", ignored=sorted(ignored))
    try:
        _load_matching(model, converted, "", report)
    except UserError as err:
        raise UserError(f"{err} (a NAS3R checkpoint loads into the `large` network)") from None
    new = [k for k in report.missing if k.startswith("appearance.")]
    report.missing = [k for k in report.missing if not k.startswith("appearance.")]
    if new:
        warnings.warn(
            f"weights {path} (NAS3R): the appearance head ({len(new)} tensors) starts afresh", stacklevel=3
        )
    _warn(report)
    return report
