"""Checkpoints of ``aesplat fit``, read the one way every command reads them.

``aesplat fit|validate|test --ckpt_path FILE|last|best``, ``aesplat predict`` and ``aesplat bench`` all come
through here:

- :func:`read_checkpoint` loads a file with torch's safe loader (tensors and plain containers; a file that
  needs any other class is refused, never unpickled) and refuses anything but a Lightning checkpoint, naming
  what the file is instead.
- :func:`checked_hparams` checks the hyper-parameters against the typed config sections before anything
  uses them: known sections and keys only, each value of its field's type. A mapping that names a class
  (``class_path``, ``init_args``, ``_class_path``, a foreign ``_instantiator``) is refused, so nothing in a
  file can make the configuration library instantiate a class.
- :func:`resolve_ckpt_path` turns ``last`` and ``best`` into a file of the run folder: ``last`` is the newest
  checkpoint that loads (a damaged one is skipped, and said so), ``best`` the one with the best validation
  score.
- :func:`load_checkpoint` rebuilds the trained model for inference (predict, bench), with the image size the
  run trained at.
"""

from __future__ import annotations

import dataclasses
import sys
import types
import typing
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, Union

import torch
from torch import Tensor

from .errors import MissingFileError, UserError
from .model import CameraSource, NetConfig
from .model.nas3r import is_nas3r_state, load_nas3r_state, nas3r_net, nas3r_variant
from .model.weights import KIND_NAMES, checkpoint_kind, read_torch_file
from .render import RasterizerConfig
from .types import DATA_RECORD

# Keys by which a configuration names a class to instantiate (jsonargparse, Lightning, Hydra).
CLASS_KEYS = frozenset({"class_path", "init_args", "dict_kwargs", "_class_path", "_target_", "__class__"})
# What LightningCLI records about how it built the module; any other value is refused.
LIGHTNING_INSTANTIATOR = "lightning.pytorch.cli.instantiate_module"


# Where `--ckpt_path last` looks in a run folder, and the names a resumable checkpoint has there.
def read_checkpoint(path: str | Path, flag: str = "--ckpt_path") -> dict:
    """A Lightning checkpoint of ``aesplat fit``, loaded safely on the CPU; UserError (one line) otherwise."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{flag} {path} is a folder: give a checkpoint file, e.g. RUN/checkpoints/last.ckpt")
    if not path.is_file():
        raise MissingFileError(f"{flag} {path} does not exist: give RUN/checkpoints/last.ckpt of `aesplat fit`")
    ckpt = read_torch_file(path, "checkpoint")
    kind = checkpoint_kind(ckpt)
    if kind != "lightning":
        hint = (
            "give it as --model.net.weights FILE instead"
            if kind != "other"
            else "give RUN/checkpoints/last.ckpt"
        )
        raise UserError(f"{flag} {path} is {KIND_NAMES[kind]}, not a Lightning checkpoint: {hint}")
    assert isinstance(ckpt, dict)
    return ckpt


# ---------------------------------------------------------------------------------------------------
# Hyper-parameters: values, never classes


def _names_a_class(value: Any, where: str) -> str | None:
    """The dotted key of the first mapping in ``value`` that names a class to instantiate, or None."""
    if isinstance(value, dict):
        for key, item in value.items():
            here = f"{where}.{key}" if where else str(key)
            if key in CLASS_KEYS:
                return here
            if key == "_instantiator" and item != LIGHTNING_INSTANTIATOR:
                return here
            if found := _names_a_class(item, here):
                return found
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            if found := _names_a_class(item, f"{where}[{i}]"):
                return found
    return None


def _type_words(annotation: Any) -> str:
    return (
        str(annotation)
        .replace("typing.", "")
        .replace("NoneType", "None")
        .replace("<class '", "")
        .replace("'>", "")
    )


def _check_value(value: Any, annotation: Any, where: str) -> None:
    """Raise ValueError naming ``where`` unless ``value`` is a plain value of type ``annotation``."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if dataclasses.is_dataclass(annotation):
        if not isinstance(value, dict):
            raise ValueError(f"{where} is {value!r}, not a section of settings")
        hints = typing.get_type_hints(annotation)
        known = {f.name for f in dataclasses.fields(annotation)}
        for key, item in value.items():
            if key not in known:
                raise ValueError(f"{where}.{key} is not a setting of this version (known: {sorted(known)})")
            _check_value(item, hints[key], f"{where}.{key}")
        return
    if origin in (Union, types.UnionType):
        for option in args:
            try:
                _check_value(value, option, where)
                return
            except ValueError:
                continue
        raise ValueError(f"{where} is {value!r}, not of type {_type_words(annotation)}")
    if origin is Literal:
        if value not in args:
            raise ValueError(f"{where} is {value!r}, not one of {', '.join(map(repr, args))}")
        return
    if origin in (tuple, list):
        if not isinstance(value, (tuple, list)):
            raise ValueError(f"{where} is {value!r}, not of type {_type_words(annotation)}")
        items = args[:1] * len(value) if origin is list or (len(args) == 2 and args[1] is Ellipsis) else args
        if len(items) != len(value):
            raise ValueError(f"{where} is {value!r}, not of type {_type_words(annotation)}")
        for i, (item, item_type) in enumerate(zip(value, items)):
            _check_value(item, item_type, f"{where}[{i}]")
        return
    plain = {
        type(None): lambda v: v is None,
        bool: lambda v: isinstance(v, bool),
        int: lambda v: isinstance(v, int) and not isinstance(v, bool),
        float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        str: lambda v: isinstance(v, str),
    }
    if annotation in plain and plain[annotation](value):
        return
    raise ValueError(f"{where} is {value!r}, not of type {_type_words(annotation)}")


def checked_hparams(ckpt: dict, path: str | Path, sections: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's hyper-parameters ``sections`` (name -> config dataclass or a type such as a Literal),
    checked: nothing in them names a class, every key is a setting of this version and every value has its
    setting's type. Returns those sections (absent ones left out); UserError (one line) otherwise."""
    hparams = ckpt.get("hyper_parameters") or {}
    if not isinstance(hparams, dict):
        raise UserError(f"checkpoint {path}: its hyper-parameters are not a mapping of settings")
    if where := _names_a_class(hparams, ""):
        raise UserError(
            f"checkpoint {path} is refused: its hyper-parameters name a class to instantiate ({where}); a "
            "checkpoint holds values, never classes: train the model again, or get the file from its author"
        )
    out = {}
    for name, annotation in sections.items():
        if name not in hparams:
            continue
        try:
            _check_value(hparams[name], annotation, name)
        except ValueError as err:
            raise UserError(f"checkpoint {path}: hyper-parameter {err}") from None
        out[name] = hparams[name]
    return out


def checkpoint_sections() -> dict[str, Any]:
    """The typed sections of a training checkpoint's hyper-parameters: those of the module's ``model``
    config section, ``model.eval`` included (the command's own, never taken from a checkpoint)."""
    from .train.evaluation import EvalConfig
    from .train.loss import LossConfig
    from .train.optim import OptimConfig

    return {"net": NetConfig, "loss": LossConfig, "optim": OptimConfig, "render": RasterizerConfig,
            "eval": EvalConfig, "cameras": CameraSource}  # fmt: skip


# ---------------------------------------------------------------------------------------------------
# `last` and `best`: checkpoints of a run folder


@dataclass(frozen=True)
class Candidate:
    """A checkpoint file of a run folder and what reading it gave: its step, or why it does not load."""

    path: Path
    step: int | None = None
    problem: str | None = None
    score: float | None = None  # the validation score it was saved with (a `best` checkpoint), if any


def run_checkpoints(run_dir: str | Path, monitor: str | None = None) -> list[Candidate]:
    """Every checkpoint of ``run_dir`` (``checkpoints/*.ckpt``, SLURM's ``hpc_ckpt_*.ckpt``), each read
    safely: its global step, the ``monitor`` score it was saved with, or why it does not load."""
    from .train.run_dir import run_checkpoint_files  # the train package imports Lightning: only when asked

    found = []
    for path in (p for p in run_checkpoint_files(run_dir) if p.is_file()):
        try:
            ckpt = read_checkpoint(path, "checkpoint")
        except UserError as err:
            found.append(Candidate(path, problem=str(err)))
            continue
        found.append(
            Candidate(path, step=int(ckpt.get("global_step", 0)), score=_saved_score(ckpt, monitor, path))
        )
    return found


def _saved_score(ckpt: dict, monitor: str | None, path: Path) -> float | None:
    """The ``monitor`` score a ``ModelCheckpoint(monitor=monitor)`` saved this file for: its own entry among
    that callback's best checkpoints (by file name, so a moved run folder still matches), or None."""
    if monitor is None:
        return None
    for key, state in (ckpt.get("callbacks") or {}).items():
        if "Checkpoint" not in str(key) or not isinstance(state, dict) or state.get("monitor") != monitor:
            continue
        for saved, score in (state.get("best_k_models") or {}).items():
            if Path(str(saved)).name == path.name:
                return float(score.item() if isinstance(score, Tensor) else score)
    return None


def resume_checkpoint(run_dir: str | Path) -> tuple[Path | None, list[str]]:
    """The checkpoint ``--ckpt_path last`` resumes from: the one at the highest step that loads (the newest
    file among equals), and the reason of each checkpoint that was skipped because it does not load."""
    candidates = run_checkpoints(run_dir)
    skipped = [c.problem for c in candidates if c.problem]
    loadable = [c for c in candidates if c.problem is None]
    if not loadable:
        return None, skipped
    chosen = max(loadable, key=lambda c: (c.step, c.path.stat().st_mtime, c.path.name.startswith("last")))
    return chosen.path, skipped


def best_checkpoint(run_dir: str | Path, monitor: str, mode: str) -> Path:
    """The checkpoint of ``run_dir`` saved with the best ``monitor`` score (``mode``: max or min)."""
    scored = [c for c in run_checkpoints(run_dir, monitor) if c.score is not None]
    if not scored:
        raise UserError(
            f"--ckpt_path best: no checkpoint in {Path(run_dir) / 'checkpoints'} was saved for its {monitor} "
            "(validation has not run yet): give --ckpt_path last or a file"
        )
    pick = max if mode == "max" else min
    return pick(scored, key=lambda c: (c.score, c.step)).path


def resolve_ckpt_path(value: str, run_dir: str | Path, monitor: str = "val/psnr", mode: str = "max",
                      fresh_if_none: bool = False) -> tuple[Path | None, list[str]]:  # fmt: skip
    """``--ckpt_path`` as a file: ``last`` (:func:`resume_checkpoint`; None when the run has none and
    ``fresh_if_none``), ``best`` (:func:`best_checkpoint`) or a path. Returns the file and what to tell the
    user about checkpoints that were skipped."""
    if value == "last":
        found, skipped = resume_checkpoint(run_dir)
        if found is None and skipped:  # never a fresh start over checkpoints that are there but damaged
            raise UserError(
                f"--ckpt_path last: no checkpoint of {run_dir} loads ({skipped[0]}); move the damaged files "
                "away to start afresh, or --overwrite"
            )
        if found is None and not fresh_if_none:
            raise MissingFileError(f"--ckpt_path last: {run_dir} holds no checkpoint (give the run's folder as "
                                   "--trainer.default_root_dir, or a checkpoint file)")  # fmt: skip
        return found, skipped
    if value == "best":
        return best_checkpoint(run_dir, monitor, mode), []
    return Path(value), []


# ---------------------------------------------------------------------------------------------------
# A trained model for inference (predict, bench)


@dataclass(frozen=True)
class LoadedCheckpoint:
    """A trained model restored from an ``aesplat fit`` checkpoint, with what the run was configured with.

    net           the checkpoint's ``net`` hyper-parameters (arguments of ``build_model``)
    render        the checkpoint's ``render`` hyper-parameters, checked and complete (backend, background,
                  options: every ``RenderSettings`` field)
    data          the ``data`` section of the run's config.yaml (None when it is not beside the checkpoint)
    trained_size  the square side the model was trained at (None when neither the checkpoint nor its run says)
    cameras       ``model.cameras`` of the run: ``predicted``, or ``dataset`` (trained with the data set's
                  cameras; its camera head is untrained, so the model needs each view's camera: forward_batch)
    config_problem  why the config.yaml beside the checkpoint is not used (None: used, or there is none)
    """

    model: torch.nn.Module
    net: dict
    render: dict
    data: dict | None
    path: Path
    trained_size: int | None = None
    cameras: str = "predicted"
    config_problem: str | None = None

    @property
    def sh_degree(self) -> int:
        return int(self.model.cfg.sh_degree)

    @property
    def patch_size(self) -> int:
        """Pixels per patch side of the model's encoder: image sides must be multiples of it."""
        return int(self.model.cfg.encoder.patch_size)

    @property
    def image_size(self) -> int:
        """The side the model was trained at; UserError when the checkpoint does not say (it is never guessed:
        the commands ask for the size instead)."""
        if self.trained_size is None:
            where = self.config_problem or "it is not in its run folder beside the run's config.yaml"
            raise UserError(
                f"{self.path} does not say which image size it was trained at ({where}): give --size, the "
                "run's data.image_size"
            )
        return self.trained_size

    @property
    def background(self) -> Tensor:
        """Render background colour [3] the run evaluated with."""
        return torch.tensor(self.render["background"], dtype=torch.float32)

    def render_options(self, device: torch.device | str = "cpu") -> dict[str, Any]:
        """Keyword arguments of ``aesplat.render.render`` as the run evaluated: its settings and background
        (``backend`` is the caller's to choose)."""
        return {**self.render["options"], "background": self.background.to(device)}


def run_config(ckpt: Path) -> tuple[dict | None, str | None]:
    """The run's config.yaml (``aesplat fit`` writes it in the run directory, the checkpoint's grandparent),
    or None; and why a config.yaml there cannot be used (None when it can, or when there is none).

    The file is data like the checkpoint: read with the safe YAML loader (a Python tag is refused, nothing
    runs). One that cannot be read, parsed or resolved, or that is not a mapping with a mapping ``data``
    section, is not used: what the commands need from it (the trained image size) most checkpoints record
    themselves, and where one does not the command asks for it by its option.
    """
    for folder in (ckpt.parent, ckpt.parent.parent):
        path = folder / "config.yaml"
        if path.is_file():
            config, problem = _read_run_config(path)
            return config, problem and f"{path} is ignored: {problem}"
    return None, None


def _read_run_config(path: Path) -> tuple[dict | None, str | None]:
    """(the config, None), or (None, why it cannot be used)."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        config = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        return None, f"not YAML this program reads ({getattr(err, 'problem', None) or err}{where})"
    except OmegaConfBaseException as err:
        return None, f"a value cannot be resolved ({str(err).splitlines()[0][:160]})"
    except (OSError, UnicodeDecodeError) as err:
        return None, f"cannot be read ({err})"
    if not isinstance(config, dict) or not isinstance(config.get("data", {}), dict):
        return None, "not a run configuration (a mapping with a `data` mapping)"
    return config, None


def trained_image_size(ckpt: dict, data: dict | None) -> int | None:
    """The image side a run trained at: recorded in the checkpoint, else its run's config.yaml; None if
    neither says."""
    record = ckpt.get(DATA_RECORD)
    if isinstance(record, dict) and isinstance(record.get("image_size"), int):
        return record["image_size"]
    size = (data or {}).get("image_size")
    return size if isinstance(size, int) and not isinstance(size, bool) else None


NAS3R_IMAGE_SIZE = 224  # NAS3R's VGGT-type networks are trained on RealEstate10K at 224 x 224


def _load_nas3r_checkpoint(ckpt: dict, path: Path, device: torch.device | str) -> LoadedCheckpoint:
    """One of NAS3R's trained networks (its Lightning ``.ckpt``) as this project's ``large`` network with
    NAS3R's own SH (``nas3r_net``); NAS3R-M or a damaged file is one line."""
    variant = nas3r_variant(ckpt["state_dict"], path)
    net = nas3r_net(variant)
    model = NetConfig(**net).build()
    load_nas3r_state(model, ckpt["state_dict"], path)
    model.to(device).eval()
    render = asdict(RasterizerConfig())
    return LoadedCheckpoint(model, net, render, None, path, trained_size=NAS3R_IMAGE_SIZE)


def load_checkpoint(
    path: str | Path, device: torch.device | str = "cpu", flag: str = "--ckpt"
) -> LoadedCheckpoint:
    """Restore the model of an ``aesplat fit`` checkpoint, or of one of NAS3R's, in eval mode on ``device``
    (no Lightning, no LPIPS).

    The model is rebuilt from the checkpoint's checked ``net`` hyper-parameters without its pretrained-weights
    file (the trained weights come from the checkpoint), then the ``model.*`` entries of the state dict are
    loaded strictly.
    """
    path = Path(path)
    ckpt = read_checkpoint(path, flag)
    if is_nas3r_state(ckpt["state_dict"]):
        return _load_nas3r_checkpoint(ckpt, path, device)
    hparams = checked_hparams(
        ckpt, path, {"net": NetConfig, "render": RasterizerConfig, "cameras": CameraSource}
    )
    if "net" not in hparams:
        raise UserError(
            f"{flag} {path} is a Lightning checkpoint without the network's settings (no 'net' "
            "hyper-parameters): "
            "give RUN/checkpoints/last.ckpt of `aesplat fit`"
        )
    net = dict(hparams["net"])
    # The trained weights come from the checkpoint, not from the run's pretrained-weights file; a few
    # inference passes do not pay back a training run's block compilation.
    model = NetConfig(**{**net, "weights": None, "compile": "none"}).build()
    state = {k[len("model.") :]: v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise UserError(
            f"{flag} {path}: its tensors do not fit the network its settings describe ({err})"
        ) from None
    model.to(device).eval()
    config, config_problem = run_config(path)
    data = (config or {}).get("data")
    render = asdict(RasterizerConfig(**dict(hparams.get("render") or {})))  # every setting, checked
    trained_size = trained_image_size(ckpt, data)
    if config_problem and trained_size is not None:  # nothing is lost without it: say so and go on
        print(f"aesplat: {config_problem}", file=sys.stderr)
    return LoadedCheckpoint(
        model, net, render, data, path, trained_size=trained_size, cameras=hparams.get("cameras", "predicted"),
        config_problem=config_problem,
    )  # fmt: skip
