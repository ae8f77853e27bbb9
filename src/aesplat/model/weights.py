"""Loading local pretrained weights by name: DINOv2 ViT/14 encoders (timm or original format), VGGT
(aggregator, camera and depth heads), NAS3R's trained networks (its Lightning ``.ckpt``: the whole network,
Gaussian head included), and a whole AESplat model from a training checkpoint of this project (``aesplat
fit``'s ``last.ckpt``, e.g. the posed warm start). Nothing is ever downloaded.

Unknown and missing keys are never silently ignored: each loader returns a :class:`WeightsReport` and warns.
"""

from __future__ import annotations

import math
import pickle
import re
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn

from ..errors import MissingFileError, UserError
from ..files import atomic_write
from .encoder import PatchEncoder, resize_position_grid


@dataclass
class WeightsReport:
    """What a weights loader did: the detected format and the keys it could not match."""

    path: str
    format: str  # "timm", "dinov2", "vggt", "nas3r" or "aesplat"
    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)  # model parameters the checkpoint lacks
    unexpected: list[str] = field(default_factory=list)  # checkpoint keys the model does not have
    ignored: list[str] = field(default_factory=list)  # known keys with no use here (VGGT's point/track heads)


def _unwrap(obj: object) -> dict[str, Tensor]:
    """Find the state dict inside a checkpoint ({"model": ...}, {"state_dict": ...}, {"teacher": ...})."""
    while isinstance(obj, dict) and not any(isinstance(v, Tensor) for v in obj.values()):
        for key in ("model", "state_dict", "teacher", "module"):
            if key in obj:
                obj = obj[key]
                break
        else:
            break
    if not isinstance(obj, dict) or not obj:
        raise UserError("the checkpoint holds no state dict (expected a dict of tensors)")
    return {k: v for k, v in obj.items() if isinstance(v, Tensor)}


def convert_encoder_state_dict(state: dict[str, Tensor]) -> tuple[dict[str, Tensor], str, list[str]]:
    """Map a timm or original-DINOv2 ViT/14 state dict onto :class:`PatchEncoder` names (DINOv2's own).

    Returns (converted state, detected format, ignored keys). Handles "module."/"backbone."/"encoder."
    prefixes, DINOv2's block chunks (``blocks.c.i.``), timm's ``reg_token`` -> ``register_tokens``, and
    position embeddings without a class-token entry (timm's ``reg4`` models), which get a zero class-token row.
    """
    out: dict[str, Tensor] = {}
    ignored: list[str] = []
    fmt = "dinov2" if any(k.endswith(("register_tokens", "mask_token")) for k in state) else "timm"
    for key, value in state.items():
        k = re.sub(r"^(module\.|backbone\.|encoder\.|model\.)+", "", key)
        k = re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k)  # DINOv2 block chunks
        if k == "reg_token":
            k = "register_tokens"
        out[k] = value
    pos = out.get("pos_embed")
    if pos is not None and pos.ndim == 3 and math.isqrt(pos.shape[1]) ** 2 == pos.shape[1]:
        out["pos_embed"] = torch.cat([pos.new_zeros(1, 1, pos.shape[2]), pos], dim=1)
    return out, fmt, ignored


def _resize_pos_embed(pos: Tensor, grid: int) -> Tensor:
    """Position embedding [1, 1 + g·g, D] of a checkpoint -> [1, 1 + grid·grid, D], as the encoder resizes."""
    return torch.cat([pos[:, :1], resize_position_grid(pos[:, 1:], (grid, grid))], dim=1)


def read_torch_file(path: str | Path, what: str) -> object:
    """Load a torch file safely (tensors and plain containers only, never arbitrary pickled objects).

    Raises :class:`MissingFileError` / :class:`UserError` naming the file (``what``: "checkpoint", "pretrained
    weights", ...) and what is wrong with it: missing, empty, truncated, not a torch file, or holding Python
    objects that could only be loaded by running code from the file.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{what} file {path} does not exist (or is not a file)")
    if path.stat().st_size == 0:
        raise UserError(f"{what} file {path} is empty")
    try:
        zipped = zipfile.is_zipfile(path)
        # a zip (the format of torch.save) is memory-mapped: a multi-GB file is not read in full
        return torch.load(path, map_location="cpu", weights_only=True, mmap=zipped)
    except OSError as err:  # the file itself cannot be read (permissions, a vanished network mount, ...)
        raise UserError(f"{what} file {path} cannot be read: {err.strerror or err}") from None
    except Exception as err:  # noqa: BLE001 - torch fails on a damaged file with anything from KeyError on
        if _refused_by_safe_loader(err):
            raise UserError(
                f"{what} file {path} holds Python objects besides tensors; it is not loaded, since that could "
                "run code from the file: give a checkpoint written by `aesplat fit`, scripts/export_weights.py "
                "or a plain state dict"
            ) from None
        zip_like = zipped or _starts_like_zip(path)
        damage = "truncated or corrupt (a damaged zip archive)" if zip_like else "not a torch file"
        raise UserError(f"{what} file {path} is {damage}; copy it again or give another file") from None


def _refused_by_safe_loader(err: Exception) -> bool:
    """Whether torch's safe loader refused a class or function the file names (torch writes "Unsupported
    global" or "unsupported GLOBAL"), as opposed to bytes it cannot read at all ("Unsupported operand")."""
    return isinstance(err, pickle.UnpicklingError) and "global" in str(err).lower()


def _starts_like_zip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(4) == b"PK\x03\x04"


def checkpoint_kind(obj: object) -> str:
    """What a loaded torch file is: ``"lightning"`` (an ``aesplat fit`` checkpoint, resumable), ``"exported"``
    (model tensors and hyper-parameters from scripts/export_weights.py), ``"weights"`` (a state dict: DINOv2,
    VGGT, ...), or ``"other"``."""
    if not isinstance(obj, dict):
        return "other"
    if "pytorch-lightning_version" in obj and "state_dict" in obj:
        return "lightning"
    if "state_dict" in obj and "hyper_parameters" in obj:
        return "exported"
    try:
        _unwrap(obj)
    except ValueError:
        return "other"
    return "weights"


KIND_NAMES = {
    "lightning": "a Lightning checkpoint of `aesplat fit`",
    "exported": "an exported weights file (scripts/export_weights.py)",
    "weights": "a weights file (a state dict, e.g. DINOv2 or VGGT)",
    "other": "not a checkpoint (no state dict of tensors)",
}


def _read_raw(path: str | Path, what: str) -> object:
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(
            f"{what} weights file {path} does not exist; give the path of a local checkpoint "
            "(.pth/.pt/.bin/.ckpt), or leave it unset for random initialisation"
        )
    return read_torch_file(path, f"{what} weights")


def _read(path: str | Path, what: str) -> dict[str, Tensor]:
    return _state_of(_read_raw(path, what), path)


def _state_of(raw: object, path: str | Path) -> dict[str, Tensor]:
    try:
        return _unwrap(raw)
    except UserError as err:
        raise UserError(f"{path}: {err}") from None


def _load_matching(
    module: nn.Module, state: dict[str, Tensor], prefix: str, report: WeightsReport, pos_grid: int | None = None
) -> None:
    """Copy the tensors of ``state`` into ``module`` by name; record loaded / missing / unexpected keys
    (with ``prefix``, the module's name in the model). A shape mismatch is an error."""
    own = module.state_dict()
    to_load: dict[str, Tensor] = {}
    for key, value in state.items():
        if key not in own:
            report.unexpected.append(prefix + key)
            continue
        if key == "pos_embed" and pos_grid is not None:
            value = _resize_pos_embed(value, pos_grid)
        if value.shape != own[key].shape:
            raise UserError(
                f"{report.path}: '{key}' has shape {tuple(value.shape)} but the model expects "
                f"{tuple(own[key].shape)} for {prefix}{key}; pick the model size (and register-token "
                "counts) that match the checkpoint"
            )
        to_load[key] = value.to(own[key].dtype)
    module.load_state_dict(to_load, strict=False)
    report.loaded += sorted(prefix + k for k in to_load)
    report.missing += sorted(prefix + k for k in set(own) - set(to_load))


def _warn(report: WeightsReport) -> None:
    if report.missing or report.unexpected:
        warnings.warn(
            f"weights {report.path} ({report.format} format): loaded {len(report.loaded)} tensors; "
            f"missing {len(report.missing)}: {report.missing[:8]}; "
            f"unexpected {len(report.unexpected)}: {report.unexpected[:8]}",
            stacklevel=3,
        )


def load_encoder_weights(encoder: PatchEncoder, path: str | Path) -> WeightsReport:
    """Load a local timm-format or original-DINOv2 ViT/14 checkpoint into ``encoder``. Never downloads.

    Keys the encoder lacks and encoder parameters the checkpoint lacks are reported with a warning and
    returned in the :class:`WeightsReport`; a shape mismatch (a checkpoint of another size) is an error.
    """
    return _load_encoder_state(encoder, _read(path, "encoder"), path)


def _load_encoder_state(
    encoder: PatchEncoder, state: dict[str, Tensor], path: str | Path, prefix: str = ""
) -> WeightsReport:
    """A ViT/14 state into ``encoder``; reported keys carry ``prefix`` (the encoder's name in the model). The
    frozen, unused ``mask_token`` is not reported missing when a file (timm's) lacks it."""
    state, fmt, ignored = convert_encoder_state_dict(state)
    report = WeightsReport(path=str(path), format=fmt, ignored=ignored)
    _load_matching(encoder, state, prefix, report, pos_grid=encoder.cfg.pos_grid)
    report.missing = [k for k in report.missing if k != prefix + "mask_token"]
    _warn(report)
    return report


def load_vggt_weights(model: nn.Module, path: str | Path) -> WeightsReport:
    """Load a local VGGT checkpoint into ``model`` (an AESplatModel) by name: its aggregator (DINOv2 patch
    embed, frame / global blocks, camera and register tokens), camera head and depth head. VGGT's point and
    track heads are listed as ignored. VGGT matches the ``large`` size."""
    return _load_vggt_state(model, _read(path, "VGGT"), path)


VGGT_PARTS = ("aggregator.", "camera_head.", "depth_head.")


def _load_vggt_state(model: nn.Module, state: dict[str, Tensor], path: str | Path) -> WeightsReport:
    enc_prefix = "aggregator.patch_embed."
    enc_state = {k[len(enc_prefix) :]: v for k, v in state.items() if k.startswith(enc_prefix)}
    enc_state, _, ignored = convert_encoder_state_dict(enc_state)
    report = WeightsReport(path=str(path), format="vggt", ignored=[enc_prefix + k for k in ignored])
    report.ignored += sorted(k for k in state if not k.startswith(VGGT_PARTS))
    encoder = model.aggregator.patch_embed
    _load_matching(encoder, enc_state, enc_prefix, report, pos_grid=encoder.cfg.pos_grid)
    rest = {k: v for k, v in state.items() if k.startswith(VGGT_PARTS) and not k.startswith(enc_prefix)}
    partial = WeightsReport(path=str(path), format="vggt")
    _load_matching(model, rest, "", partial)
    report.loaded += partial.loaded
    report.unexpected += partial.unexpected
    # the model's tensors outside what VGGT has (the Gaussian head, appearance) are new, not missing
    vggt_has = [k for k in partial.missing if k.startswith(VGGT_PARTS) and not k.startswith(enc_prefix)]
    report.missing += sorted(vggt_has)
    _warn(report)
    return report


def load_pretrained_weights(model: nn.Module, path: str | Path) -> WeightsReport:
    """Load a local checkpoint, whichever of the supported kinds it is: a VGGT checkpoint (keys under
    ``aggregator.``), otherwise a timm or DINOv2 ViT/14 into the patch encoder."""
    return _load_backbone_state(model, _read(path, "pretrained"), path)


def _load_backbone_state(model: nn.Module, state: dict[str, Tensor], path: str | Path) -> WeightsReport:
    """A VGGT state (keys under ``aggregator.``) into the model, else a ViT/14 into its patch encoder."""
    if any(k.startswith("aggregator.") for k in state):
        return _load_vggt_state(model, state, path)
    return _load_encoder_state(model.aggregator.patch_embed, state, path, "aggregator.patch_embed.")


AESPLAT_PREFIX = "model."  # where the LightningModule keeps the AESplatModel in its state dict


def is_aesplat_checkpoint(state: dict[str, Tensor]) -> bool:
    """Whether a state dict is an AESplat training checkpoint's (the module's keys: ``model.camera_head.…``)."""
    return any(k.startswith(AESPLAT_PREFIX + "camera_head.") for k in state)


def _load_aesplat_state(
    model: nn.Module, state: dict[str, Tensor], path: str | Path, trained_with: dict | None = None
) -> WeightsReport:
    """Every tensor of the checkpoint's model into ``model`` (an AESplatModel of the same architecture).
    The module's other entries (metrics) are ignored; a shape mismatch is an error naming the checkpoint's
    network settings (``trained_with``: its ``hyper_parameters["net"]``). An appearance head of another view
    aggregation than ``model``'s is left out with a warning (a ``pool`` run from a ``concat`` warm start)."""
    report = WeightsReport(path=str(path), format="aesplat")
    report.ignored = sorted(k for k in state if not k.startswith(AESPLAT_PREFIX))
    own = {k[len(AESPLAT_PREFIX) :]: v for k, v in state.items() if k.startswith(AESPLAT_PREFIX)}
    saved_kind = (trained_with or {}).get("view_aggregation", "concat")  # older checkpoints: the paper's head
    kind = getattr(getattr(model, "cfg", None), "view_aggregation", saved_kind)
    if saved_kind != kind:  # another head's layout: the rest of the network loads, this head starts afresh
        head = sorted(k for k in own if k.startswith("appearance."))
        report.ignored += [AESPLAT_PREFIX + k for k in head]
        own = {k: v for k, v in own.items() if not k.startswith("appearance.")}
        warnings.warn(
            f"weights {path}: its appearance head is view_aggregation {saved_kind}, this model's {kind}; "
            f"the {len(head)} appearance tensors are not loaded (that head starts from its initialisation)",
            stacklevel=3,
        )
    saved_scales = ((trained_with or {}).get("options") or {}).get("scale_mode") or "absolute"
    scales = getattr(getattr(model, "cfg", None), "scale_mode", saved_scales)
    if saved_scales != scales:  # the same tensors, another meaning: loaded, and said
        warnings.warn(
            f"weights {path}: its Gaussian head was trained with scale_mode {saved_scales}, this model's is "
            f"{scales}; its scale outputs load but meant other sizes (a warm start made with {scales} fits)",
            stacklevel=3,
        )
    try:
        _load_matching(model, own, "", report)
    except ValueError as err:
        keys = ("size", "appearance", "view_aggregation", "sh_degree", "options")
        settings = {k: trained_with.get(k) for k in keys} if trained_with else {}
        raise UserError(f"{err}. The checkpoint was trained with model.net {settings}") from None
    _warn(report)
    return report


def load_weights(model: nn.Module, path: str | Path) -> WeightsReport:
    """What ``build_model(weights=...)`` calls: an AESplat training checkpoint into the whole ``model``, a
    NAS3R checkpoint into all of it but the appearance head (``nas3r.py``), else (``load_pretrained_weights``)
    a VGGT or DINOv2 checkpoint into its trunk (and VGGT's camera and depth heads)."""
    raw = _read_raw(path, "pretrained")  # read once: VGGT checkpoints are several GB
    state = _state_of(raw, path)
    if is_aesplat_checkpoint(state):
        hparams = raw.get("hyper_parameters") if isinstance(raw, dict) else None
        return _load_aesplat_state(model, state, path, (hparams or {}).get("net"))
    from .nas3r import is_nas3r_state, load_nas3r_state

    if is_nas3r_state(state):
        return load_nas3r_state(model, state, path)
    return _load_backbone_state(model, state, path)


def export_weights(checkpoint: str | Path, out: str | Path, note: str = "") -> Path:
    """Write the model part of an ``aesplat fit`` checkpoint to ``out``: the model's tensors (fp32, the
    module's ``model.`` keys, nothing of the optimizer, metrics or loops) and the run's hyper-parameters, which
    ``model.net.weights`` loads like the checkpoint itself (about a third of its size). ``note`` is kept
    beside them (e.g. the command that made it). Written whole or not at all (an earlier ``out`` stays as it
    was when the write fails)."""
    raw = _read_raw(checkpoint, "training")
    state = _state_of(raw, checkpoint)
    if not is_aesplat_checkpoint(state):
        raise ValueError(
            f"{checkpoint} is not an `aesplat fit` checkpoint (no {AESPLAT_PREFIX}camera_head.* keys)"
        )
    model_state = {k: v.detach().float().clone() for k, v in state.items() if k.startswith(AESPLAT_PREFIX)}
    hparams = raw.get("hyper_parameters", {}) if isinstance(raw, dict) else {}
    step = raw.get("global_step") if isinstance(raw, dict) else None
    payload = {"state_dict": model_state, "hyper_parameters": hparams, "global_step": step, "note": note}
    return atomic_write(
        out, lambda f: torch.save(payload, f)
    )  # whole or not at all: a full disk keeps the old file
