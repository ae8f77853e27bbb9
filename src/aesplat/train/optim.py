"""AdamW with named parameter groups, a warm-up + cosine schedule, and the non-finite step check.

Groups come from the model's ``named_parameter_groups()`` (keys ``appearance``, ``backbone``, ``rest``):
``appearance`` trains at its own learning rate (3e-4 in the paper), ``rest`` at the base rate, and a
*pretrained* ``backbone`` at a fraction of it. Each group is split once more into a weight-decay part and a
no-decay part (norms, biases, tokens), so every trainable parameter sits in exactly one optimizer group.
When skipped steps stop being rare, ``skip_guard.SkipGuard`` ends the run.

``impl`` picks torch's AdamW kernel: ``fused`` (one kernel over all parameters; CUDA and CPU since torch 2.4),
``foreach`` (multi-tensor ops) or ``for_loop`` (one parameter at a time, the reference). All three skip a
parameter whose ``grad`` is None; ``fused`` also skips a whole step on a device-side flag (``skipped_when``),
so with it a training step needs no host synchronisation to decide whether to skip.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor, nn

GROUP_NAMES = ("appearance", "backbone", "rest")
OPTIM_IMPLS = ("auto", "fused", "foreach", "for_loop")
_FUSED_DEVICES = ("cuda", "cpu")  # device types with a fused AdamW kernel in every supported torch (>= 2.4)
_NO_DECAY_WORDS = ("norm", "bias", "token", "pos_embed", "register", "embedding")


@dataclass
class OptimConfig:
    """Optimizer and schedule settings (docs/training.md, "What a training step does")."""

    lr: float = 1e-4  # base learning rate (`rest`)
    appearance_lr: float = 3e-4  # view-dependent head + GVSRE MLP
    backbone_lr_scale: float = 0.1  # applied only when pretrained backbone weights were loaded
    weight_decay: float = 0.05  # AdamW's, on matrices and kernels only (not norms, biases, tokens)
    betas: tuple[float, float] = (0.9, 0.95)  # AdamW's moment decay rates
    warmup_steps: int = 2000  # linear warm-up from 0, then the cosine
    total_steps: int | None = None  # length of the cosine; None = trainer.max_steps
    min_lr_ratio: float = 0.0  # the cosine ends at min_lr_ratio * each group's peak rate
    grad_clip: float = 0.5  # gradient-norm clipping; 0 disables
    # Non-finite steps are skipped; the run stops when skipping is no longer rare (train/skip_guard.py).
    max_skipped_fraction: float = 0.1  # stop when more than this share of the last `skip_window` steps skipped
    skip_window: int = 100  # steps over which max_skipped_fraction is judged
    max_consecutive_skips: int = 10  # stop after this many skipped steps in a row; 0 disables
    anomaly_report: bool = True  # re-run the first skipped step under anomaly detection and report the op
    impl: str = "auto"  # auto | fused | foreach | for_loop; auto = fused on CUDA and CPU, else foreach

    def __post_init__(self) -> None:
        if self.impl not in OPTIM_IMPLS:
            raise ValueError(f"unknown optim.impl {self.impl!r}; choose one of {', '.join(OPTIM_IMPLS)}")


def uses_weight_decay(name: str, param: Tensor) -> bool:
    """Matrices and conv kernels decay; norms, biases, tokens and embeddings (vectors or by name) do not."""
    lowered = name.lower()
    return param.ndim >= 2 and not any(word in lowered for word in _NO_DECAY_WORDS)


def group_learning_rates(cfg: OptimConfig, pretrained_backbone: bool) -> dict[str, float]:
    """Peak learning rate of each named group."""
    backbone = cfg.lr * cfg.backbone_lr_scale if pretrained_backbone else cfg.lr
    return {"appearance": cfg.appearance_lr, "backbone": backbone, "rest": cfg.lr}


def build_param_groups(
    named_groups: dict[str, list[tuple[str, nn.Parameter]]], cfg: OptimConfig, pretrained_backbone: bool
) -> list[dict]:
    """Optimizer groups from the model's named groups; frozen parameters are left out.

    Returns dicts with ``params``, ``lr``, ``weight_decay``, ``name`` (appearance | backbone | rest) and
    ``decay`` (bool). Raises if a group name is unknown or a parameter appears twice.
    """
    unknown = set(named_groups) - set(GROUP_NAMES)
    if unknown:
        raise ValueError(f"unknown parameter group(s) {sorted(unknown)}; expected a subset of {GROUP_NAMES}")
    lrs = group_learning_rates(cfg, pretrained_backbone)
    seen: dict[int, str] = {}
    groups = []
    for group in GROUP_NAMES:
        split: dict[bool, list[nn.Parameter]] = {True: [], False: []}
        for name, param in named_groups.get(group, []):
            if not param.requires_grad:
                continue
            if id(param) in seen:
                raise ValueError(f"parameter {name} is in group {group!r} and also in {seen[id(param)]!r}")
            seen[id(param)] = group
            split[uses_weight_decay(name, param)].append(param)
        for decay, params in split.items():
            if params:
                wd = cfg.weight_decay if decay else 0.0
                groups.append({"params": params, "lr": lrs[group], "weight_decay": wd, "name": group,
                               "decay": decay})  # fmt: skip
    return groups


def resolve_impl(impl: str, params: Iterable[Tensor]) -> str:
    """The AdamW kernel to use: ``impl`` itself, or for ``auto`` fused when every parameter lives on a device
    type with a fused kernel (CUDA, CPU), else foreach."""
    if impl not in OPTIM_IMPLS:
        raise ValueError(f"unknown optim.impl {impl!r}; choose one of {', '.join(OPTIM_IMPLS)}")
    if impl != "auto":
        return impl
    devices = {p.device.type for p in params}
    return "fused" if devices and devices <= set(_FUSED_DEVICES) else "foreach"


class WarmupCosine:
    """Learning-rate multiplier: linear warm-up from ~0 to 1, then cosine decay to ``min_ratio``.

    A callable object (not a lambda) so ``LambdaLR.state_dict`` stores its settings with the checkpoint.
    """

    def __init__(self, warmup_steps: int, total_steps: int, min_ratio: float = 0.0) -> None:
        self.warmup_steps = max(0, int(warmup_steps))
        self.total_steps = max(self.warmup_steps + 1, int(total_steps))
        self.min_ratio = float(min_ratio)

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        progress = min(1.0, (step - self.warmup_steps) / (self.total_steps - self.warmup_steps))
        return self.min_ratio + (1.0 - self.min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def build_optimizer(
    named_groups: dict[str, list[tuple[str, nn.Parameter]]],
    cfg: OptimConfig,
    pretrained_backbone: bool,
    total_steps: int | None = None,
) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """One AdamW over the named groups and its per-step warm-up + cosine scheduler.

    The cosine spans ``cfg.total_steps``, else ``total_steps`` (the trainer's max_steps). Build it after the
    parameters are on their device: ``impl: auto`` looks at where they live.
    """
    groups = build_param_groups(named_groups, cfg, pretrained_backbone)
    impl = resolve_impl(cfg.impl, (p for g in groups for p in g["params"]))
    kernel = {"fused": {"fused": True}, "foreach": {"foreach": True}, "for_loop": {"foreach": False}}[impl]
    optimizer = torch.optim.AdamW(groups, betas=tuple(cfg.betas), weight_decay=cfg.weight_decay, **kernel)
    length = cfg.total_steps or total_steps
    if not length or length < 0:
        raise ValueError("the cosine schedule needs a length: set trainer.max_steps or model.optim.total_steps")
    schedule = WarmupCosine(cfg.warmup_steps, length, cfg.min_lr_ratio)
    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)


def current_learning_rates(optimizer: torch.optim.Optimizer) -> dict[str, float]:
    """Learning rate of each named group (decay and no-decay halves share it)."""
    return {group.get("name", str(i)): group["lr"] for i, group in enumerate(optimizer.param_groups)}


def clip_and_check(parameters: Iterable[Tensor], max_norm: float, loss: Tensor) -> tuple[Tensor, Tensor]:
    """Clip the gradient norm in place (when ``max_norm`` > 0) and flag a non-finite loss or gradient.

    Returns (total gradient norm before clipping, ``found_inf``): a float32 scalar on the gradients' device,
    1.0 when the loss or any gradient is NaN/Inf, else 0.0. Nothing here waits for the device (no ``.item()``,
    no ``bool``): the flag goes to ``skipped_when`` as it is, and the host reads it later, with the logs.
    """
    grads = [p for p in parameters if p.grad is not None]
    if max_norm > 0:
        norm = torch.nn.utils.clip_grad_norm_(grads, max_norm)
    elif grads:
        norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm([p.grad for p in grads])))
    else:
        norm = torch.zeros((), device=loss.device)
    # The norm is NaN/Inf when any gradient is; a NaN loss with finite gradients is caught by the loss itself.
    finite = torch.isfinite(norm) & torch.isfinite(loss.detach().to(norm.device)).all()
    return norm, (~finite).float()


@contextmanager
def skipped_when(optimizer: torch.optim.Optimizer, found_inf: Tensor) -> Iterator[None]:
    """Within the block, ``optimizer.step()`` changes nothing when ``found_inf`` (``clip_and_check``) is 1.

    Fused AdamW takes the flag on the device, as ``torch.amp.GradScaler`` hands it over: the kernel skips the
    update and gives the step counters back, with no host synchronisation. The foreach and for-loop kernels
    take no such flag, so for them the host reads it (one synchronisation) and drops the gradients.
    Either way parameters, moments and step counters stay bit-identical on a flagged step.
    """
    if optimizer.defaults.get("fused"):
        optimizer.found_inf = found_inf.float()  # read by torch.optim.Adam/AdamW.step
        try:
            yield
        finally:
            del optimizer.found_inf
    else:
        if found_inf.item():
            discard_gradients(optimizer)
        yield


def discard_gradients(optimizer: torch.optim.Optimizer) -> None:
    """Drop every gradient so the following ``optimizer.step()`` changes nothing.

    AdamW (for-loop, foreach and fused alike) skips parameters whose ``grad`` is None: parameters, moments
    and step counts stay bit-identical, while the trainer still counts the step (schedule and curriculum stay
    aligned with batches).
    """
    optimizer.zero_grad(set_to_none=True)
