"""The values of a configuration, checked before a command writes or loads anything.

``aesplat fit|validate|test`` parse the command line and the ``-c`` files into one configuration; before the
run folder, wandb or the model exist, :func:`check_config` builds each config section's dataclass (so their
own checks run: unknown choices, unknown options) and checks every value against the ranges below. The first
value out of range stops the command with one line naming the key, the value and what it must be, so a run
never starts on a negative learning rate, and never fails at its first step on an image size its patch does
not divide, an SH degree the renderer has no basis for, or zero steps to train.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import UserError
from .geometry.sh import MAX_SH_DEGREE
from .train.signals import MAX_TIMEOUT, MIN_TIMEOUT


@dataclass(frozen=True)
class Rule:
    """``key`` (dotted, in the parsed configuration) must pass ``test``; ``must`` says what it must be."""

    key: str
    test: Callable[[Any], bool]
    must: str
    commands: tuple[str, ...] = ("fit", "validate", "test")
    optional: bool = False  # None passes (the setting is off, or left to its default)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def positive(v: Any) -> bool:
    return _number(v) and v > 0


def at_least_zero(v: Any) -> bool:
    return _number(v) and v >= 0


def at_least_one(v: Any) -> bool:
    return _number(v) and v >= 1


def fraction(v: Any) -> bool:
    return _number(v) and 0 <= v <= 1


def colour(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == 3 and all(fraction(c) for c in v)


def momentum(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == 2 and all(_number(c) and 0 <= c < 1 for c in v)


RULES: tuple[Rule, ...] = (
    Rule(
        "model.net.sh_degree",
        lambda v: isinstance(v, int) and 0 <= v <= MAX_SH_DEGREE,
        f"an SH degree in 0..{MAX_SH_DEGREE} (the renderer's bases)",
    ),
    Rule("model.net.near", positive, "a positive depth"),
    Rule("model.net.options.patch_size", at_least_one, "a patch side of 1 pixel or more", optional=True),
    Rule("model.net.options.pixel_offset", fraction, "a place in the pixel in [0, 1] (0: corner, 0.5: centre)",
         optional=True),  # fmt: skip
    Rule(
        "model.net.options.num_context_views",
        lambda v: isinstance(v, int) and v >= 2,
        "2 or more",
        optional=True,
    ),
    Rule("model.optim.lr", positive, "a positive learning rate"),
    Rule("model.optim.appearance_lr", positive, "a positive learning rate"),
    Rule("model.optim.backbone_lr_scale", positive, "a positive factor"),
    Rule("model.optim.weight_decay", at_least_zero, "0 or more"),
    Rule("model.optim.betas", momentum, "two decay rates in [0, 1)"),
    Rule("model.optim.warmup_steps", at_least_zero, "0 or more steps"),
    Rule("model.optim.total_steps", at_least_one, "1 or more steps", optional=True),
    Rule("model.optim.min_lr_ratio", fraction, "a ratio in [0, 1]"),
    Rule("model.optim.grad_clip", at_least_zero, "0 (off) or a positive gradient norm"),
    Rule("model.optim.max_skipped_fraction", fraction, "a fraction in [0, 1]"),
    Rule("model.optim.skip_window", at_least_one, "1 or more steps"),
    Rule("model.optim.max_consecutive_skips", at_least_zero, "0 (off) or more steps"),
    Rule("model.loss.mse_weight", at_least_zero, "a weight of 0 or more"),
    Rule("model.loss.lpips_weight", at_least_zero, "a weight of 0 or more"),
    Rule("model.render.background", colour, "an RGB colour, three values in [0, 1]"),
    Rule("model.eval.num_sample_renders", at_least_zero, "0 or more scenes"),
    Rule("model.eval.log_images_every_n_steps", at_least_zero, "0 (off) or more steps"),
    Rule("data.train_batches_per_epoch", at_least_one, "1 or more batches", commands=("fit",)),
    Rule("data.seed", lambda v: isinstance(v, int) and v >= 0, "a seed of 0 or more"),
    Rule(
        "trainer.accumulate_grad_batches",
        lambda v: v == 1,
        "1: the module steps its optimizer itself once per batch; raise data.batch_size instead",
        commands=("fit",),
        optional=True,
    ),
    Rule(
        "trainer.val_check_interval",
        lambda v: (isinstance(v, int) and v >= 1) or (isinstance(v, float) and 0 < v <= 1),
        "1 or more steps, or a fraction of an epoch in (0, 1]",
        commands=("fit",),
        optional=True,
    ),
    Rule("trainer.check_val_every_n_epoch", at_least_one, "1 or more epochs", commands=("fit",), optional=True),
    Rule("trainer.log_every_n_steps", at_least_one, "1 or more steps", commands=("fit",), optional=True),
    Rule(
        "trainer.max_steps",
        lambda v: v == -1 or at_least_one(v),
        "-1 (no limit) or 1 or more steps: 0 trains nothing",
        commands=("fit",),
    ),  # fmt: skip
    Rule(
        "distributed.timeout",
        lambda v: _number(v) and MIN_TIMEOUT <= v <= MAX_TIMEOUT,
        f"{MIN_TIMEOUT:g} to {MAX_TIMEOUT:g} seconds (7 days): every rank must start and join the process "
        "group within it",
    ),
    Rule(
        "last_checkpoint.every_n_train_steps",
        at_least_zero,
        "0 (only the final save) or more steps",
        commands=("fit",),
        optional=True,
    ),
)


def _value(cfg: Any, key: str) -> tuple[bool, Any]:
    """(present, value) of a dotted key in a jsonargparse Namespace or a nested dict."""
    node = cfg
    for part in key.split("."):
        if node is None:
            return False, None
        getter = getattr(node, "get", None)
        if getter is None:
            return False, None
        if part not in node:
            return False, None
        node = getter(part)
    return True, node


def _section(cfg: Any, key: str) -> dict:
    present, value = _value(cfg, key)
    if not present or value is None:
        return {}
    return value.as_dict() if hasattr(value, "as_dict") else dict(value)


def check_config(command: str, cfg: Any) -> None:
    """Check the values of a parsed ``aesplat fit|validate|test`` configuration (the subcommand's Namespace);
    UserError "invalid configuration: KEY = VALUE: it must be ..." for the first one out of range."""
    from .data.datamodule import RANGES
    from .data.remote import DOWNLOAD_RANGES
    from .model import APPEARANCE_MODES, SIZES, NetConfig
    from .render import RasterizerConfig
    from .train.evaluation import EvalConfig
    from .train.loss import LossConfig
    from .train.optim import OptimConfig

    sections = {"model.net": NetConfig, "model.loss": LossConfig, "model.optim": OptimConfig,
                "model.render": RasterizerConfig, "model.eval": EvalConfig}  # fmt: skip
    built = {}
    for key, cls in sections.items():
        try:
            built[key] = cls(**_section(cfg, key))
        except (TypeError, ValueError) as err:
            raise UserError(f"invalid configuration: {err}") from None
    net = built["model.net"]
    if net.size not in SIZES:
        raise UserError(
            f"invalid configuration: unknown model size {net.size!r}; choose one of {', '.join(SIZES)}"
        )
    if net.appearance not in APPEARANCE_MODES:
        raise UserError(f"invalid configuration: unknown appearance {net.appearance!r}; choose one of "
                        f"{', '.join(APPEARANCE_MODES)}")  # fmt: skip
    # The data module's ranges (checked again when it is built): here before anything is written.
    data_rules = [Rule(f"data.{name}", at_least_one if lowest == 1 else at_least_zero, must, optional=optional)
                  for name, (lowest, must, optional) in RANGES.items()]  # fmt: skip
    data_rules += [Rule(f"data.{name}", test, must) for name, (test, must) in DOWNLOAD_RANGES.items()]
    first = next(i for i, rule in enumerate(RULES) if rule.key.startswith("data."))
    for rule in (*RULES[:first], *data_rules, *RULES[first:]):
        if command not in rule.commands:
            continue
        present, value = _value(cfg, rule.key)
        if not present or (value is None and rule.optional):
            continue
        if not rule.test(value):
            raise UserError(f"invalid configuration: {rule.key} = {value!r}: it must be {rule.must}")
    if not net.far > net.near:
        raise UserError(
            f"invalid configuration: model.net.far = {net.far!r}: it must be more than model.net.near "
            f"({net.near!r})"
        )
    patch = net.options.patch_size or SIZES[net.size].encoder.patch_size
    present, size = _value(cfg, "data.image_size")
    if present and size % patch:
        raise UserError(
            f"invalid configuration: data.image_size = {size}: it must be a multiple of the patch size {patch} "
            f"(e.g. {max(patch, size // patch * patch)} or {(size // patch + 1) * patch})"
        )
