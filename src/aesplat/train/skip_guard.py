"""The non-finite step guard: skip a rare bad step, stop a run that keeps skipping, and explain the first one.

Skipping a step whose loss or gradients are not finite is right when it is rare (one odd batch). A run that
skips a large share of its steps is broken while it looks alive, so the guard stops it with an error when more
than ``max_skipped_fraction`` of the last ``skip_window`` steps, or ``max_consecutive_skips`` steps in a row,
were skipped. On the first skipped step it re-runs that step's forward and backward once under
``torch.autograd.detect_anomaly`` and reports which operation produced the first non-finite value and where in
the source it was called (a warning, and ``nonfinite_step<N>.txt`` in the run directory). Its counters are
part of the checkpoint, so a resumed run judges the same window.

The skip itself is decided on the device (``optim.skipped_when``); the host learns of it later, so that a
training step need not wait for the device: ``defer`` keeps each step's flag and ``resolve`` accounts the
pending steps in order once their flags have been read (the module reads them with its logs, every
``trainer.log_every_n_steps`` steps, and before a checkpoint and at the end of training). A run that keeps
skipping is therefore stopped at the first read after the limit was crossed, and the message names the step
that crossed it. The first skipped step is re-run with its own batch; when it was read some steps later, the
weights are those of the read (unchanged by the skipped step itself) and its gradients are gone.
"""

from __future__ import annotations

import re
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from .optim import OptimConfig, discard_gradients

_FRAME = re.compile(r'File "(?P<file>[^"]+)", line (?P<line>\d+), in (?P<func>\S+)\n\s*(?P<code>[^\n]*)')


class PersistentNonFiniteSteps(RuntimeError):
    """Too many training steps were skipped for a non-finite loss or gradient: the run is stopped."""


@dataclass
class AnomalyReport:
    """What re-running one non-finite step under anomaly detection found."""

    step: int
    bad_parameters: list[str]  # parameters whose gradient was not finite in the skipped step
    forward_module: str | None = None  # first (innermost) module whose output was not finite on the re-run
    loss_finite: bool = True  # the re-run's loss
    operation: str | None = None  # autograd function whose backward returned NaN/Inf (e.g. SqrtBackward0)
    source: str | None = None  # innermost project frame of that operation's forward call: file:line: code
    traceback: str = ""  # the forward call's full traceback, as anomaly detection prints it
    error: str | None = None  # a re-run that failed for another reason
    bad_parameter_count: int = 0  # bad_parameters lists the first few of them
    gradients_known: bool = True  # False: the step was read after its gradients were gone (no names)

    def summary(self) -> str:
        """One paragraph: where the first non-finite value came from."""
        where = []
        if self.operation:
            where.append(f"backward of {self.operation}, whose forward call is {self.source or 'unknown'}")
        if self.forward_module is not None:
            where.append(f"forward output of module '{self.forward_module or '(the model)'}' not finite")
        if not self.loss_finite and self.forward_module is None:
            where.append("the loss was not finite while every module output was (the loss or the renderer)")
        if self.error:
            where.append(f"the re-run failed: {self.error}")
        if not where:
            where.append("the re-run was finite throughout (a non-deterministic or data-dependent cause)")
        bad = ", ".join(
            self.bad_parameters + (["..."] if self.bad_parameter_count > len(self.bad_parameters) else [])
        )
        gradients = (
            f"{self.bad_parameter_count} parameter(s) had non-finite gradients{f' ({bad})' if bad else ''}."
            if self.gradients_known
            else "Its gradients were gone when the skip was read, so no parameter is named."
        )
        return f"first skipped step {self.step}: {'; '.join(where)}. {gradients}"

    def text(self) -> str:
        """The full report written to the run directory."""
        return (
            f"{self.summary()}\n\nTraceback of the forward call (anomaly detection):\n{self.traceback or '-'}\n"
        )


class SkipGuard:
    """Counts skipped steps over a sliding window and stops the run when they are no longer rare.

    ``defer(step, flag, rerun)`` is called once per training step with the step's device-side flag (the same on
    every DDP rank); ``resolve(flags, ...)`` accounts the deferred steps once the host has read their flags:
    ``skip(...)`` on the skipped ones, then ``record(step, skipped)`` for each.
    """

    def __init__(self, cfg: OptimConfig) -> None:
        if cfg.skip_window < 1 or not 0.0 <= cfg.max_skipped_fraction <= 1.0 or cfg.max_consecutive_skips < 0:
            raise ValueError(
                "model.optim: need skip_window >= 1, 0 <= max_skipped_fraction <= 1 and max_consecutive_skips "
                f">= 0 (0 disables a limit), got {cfg.skip_window}, {cfg.max_skipped_fraction}, "
                f"{cfg.max_consecutive_skips}"
            )
        self.cfg = cfg
        self.recent: deque[bool] = deque(maxlen=max(1, cfg.skip_window))
        self.consecutive = 0
        self.total = 0
        self.first_report = ""  # summary of the first skipped step's anomaly re-run ("" until there is one)
        self.pending: list[tuple[int, Tensor, Callable[[], Tensor] | None]] = []  # deferred, not yet read

    @property
    def explains_next_skip(self) -> bool:
        """Whether the next skipped step will be re-run under anomaly detection (the first one only)."""
        return self.total == 0 and self.cfg.anomaly_report

    def defer(self, step: int, found_inf: Tensor, rerun: Callable[[], Tensor] | None = None) -> None:
        """Keep a step's flag (a device scalar, 1 = skipped) until ``resolve``; ``rerun`` recomputes the step's
        loss, kept only while the first skipped step is still to be explained."""
        self.pending.append((step, found_inf, rerun if self.explains_next_skip else None))

    def pending_flags(self) -> list[Tensor]:
        """The deferred steps' flags, in step order (read them on the host in one transfer)."""
        return [flag for _, flag, _ in self.pending]

    def resolve(self, flags: Sequence[float], model: nn.Module, optimizer: torch.optim.Optimizer,
                run_dir: str | Path, rank: int = 0, current_step: int | None = None) -> None:  # fmt: skip
        """Account the deferred steps, ``flags`` being their flags as read on the host: count (and explain) the
        skipped ones and judge the window step by step; raises ``PersistentNonFiniteSteps`` like ``record``.
        ``current_step``: the step whose gradients are still in the parameters (named in the report)."""
        pending, self.pending = self.pending, []
        if len(flags) != len(pending):
            raise ValueError(f"{len(pending)} deferred steps but {len(flags)} flags")
        for (step, _, rerun), flag in zip(pending, flags):
            skipped = flag > 0
            if skipped:
                self.skip(step, model, optimizer, rerun, run_dir, rank, own_gradients=step == current_step)
            try:
                self.record(step, skipped)
            except PersistentNonFiniteSteps as err:
                if current_step is None or current_step == step:
                    raise
                raise PersistentNonFiniteSteps(f"{err} (Skips are read with the logs: this was read at step "
                                               f"{current_step}.)") from None  # fmt: skip

    def skip(self, step: int, model: nn.Module, optimizer: torch.optim.Optimizer,
             rerun: Callable[[], Tensor] | None, run_dir: str | Path, rank: int = 0,
             own_gradients: bool = True) -> None:  # fmt: skip
        """Count a skipped step and drop the gradients in the parameters; explain the step if it is the first.

        ``rerun`` recomputes this step's loss (forward, rendering and loss, not the backward); None: no re-run.
        ``own_gradients``: the parameters still hold this step's gradients (their non-finite ones are named).
        """
        if rank == 0:  # every rank takes the same decision; one warning is enough
            warnings.warn(f"step {step}: non-finite loss or gradient, update skipped", stacklevel=2)
        first = self.explains_next_skip and rerun is not None
        bad = non_finite_gradients(model) if first and own_gradients else ([], 0)
        discard_gradients(optimizer)  # before the re-run: its graph and gradients need the memory
        if first:
            report = explain_non_finite_step(step, model, rerun, *bad)
            report.gradients_known = own_gradients
            self.first_report = report.summary()
            path = Path(run_dir) / f"nonfinite_step{step}{f'_rank{rank}' if rank else ''}.txt"
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(report.text())
                self.first_report += f" Full report: {path}"
            except OSError as err:  # a read-only run directory must not end the run here
                self.first_report += f" (report not written: {err})"
            warnings.warn(f"non-finite training step explained: {self.first_report}", stacklevel=2)
        self.total += 1

    def record(self, step: int, skipped: bool) -> None:
        """Account one training step; raise ``PersistentNonFiniteSteps`` when skipping is no longer rare."""
        self.recent.append(bool(skipped))
        self.consecutive = self.consecutive + 1 if skipped else 0
        cfg = self.cfg
        in_window = sum(self.recent)
        too_many = cfg.max_skipped_fraction > 0 and in_window > cfg.max_skipped_fraction * cfg.skip_window
        in_a_row = 0 < cfg.max_consecutive_skips <= self.consecutive
        if not (too_many or in_a_row):
            return
        what = (f"{self.consecutive} steps in a row" if in_a_row
                else f"{in_window} of the last {len(self.recent)} steps")  # fmt: skip
        origin = (
            f"Where it comes from: {self.first_report}"
            if self.first_report
            else "The first skipped step was not re-run under anomaly detection (model.optim.anomaly_report)."
        )
        raise PersistentNonFiniteSteps(
            f"training stopped at step {step}: {what} were skipped because their loss or gradients were not "
            f"finite ({self.total} skipped in all). A run that skips this often is broken, not unlucky: its "
            f"loss curve and checkpoints no longer mean what they seem. Limits: more than "
            f"{cfg.max_skipped_fraction:.0%} of the last {cfg.skip_window} steps "
            f"(model.optim.max_skipped_fraction, model.optim.skip_window) or {cfg.max_consecutive_skips} in a "
            f"row (model.optim.max_consecutive_skips); 0 disables either. {origin}"
        )  # fmt: skip

    def state_dict(self) -> dict:
        """Plain values only (checkpoints load with ``weights_only=True``)."""
        return {"recent": list(self.recent), "consecutive": self.consecutive, "total": self.total,
                "first_report": self.first_report}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        self.recent.clear()
        self.recent.extend(bool(s) for s in state.get("recent", []))
        self.consecutive = int(state.get("consecutive", 0))
        self.total = int(state.get("total", 0))
        self.first_report = str(state.get("first_report", ""))


def non_finite_gradients(model: nn.Module, limit: int = 8) -> tuple[list[str], int]:
    """The first ``limit`` names of parameters whose gradient holds NaN or Inf, and how many there are."""
    bad = [
        name for name, p in model.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()
    ]
    return bad[:limit], len(bad)


def explain_non_finite_step(
    step: int, model: nn.Module, rerun: Callable[[], Tensor], bad_parameters: list[str], bad_count: int
) -> AnomalyReport:
    """Re-run a step's forward and backward once under anomaly detection and say what went non-finite first.

    Forward hooks find the first module whose output is not finite; ``torch.autograd.detect_anomaly`` names
    the first backward function returning NaN/Inf and the forward line that created it. Gradients are taken
    with ``torch.autograd.grad`` (nothing accumulates into ``.grad``, no DDP hook fires), under a forked RNG
    so the run's random stream is the same with or without this report.
    """
    report = AnomalyReport(step, bad_parameters, bad_parameter_count=bad_count)
    names = {module: name for name, module in model.named_modules()}

    def hook(module: nn.Module, args, output) -> None:
        if report.forward_module is None and not _all_finite(output):
            report.forward_module = names[module]

    handles = [m.register_forward_hook(hook) for m in names]
    params = [p for p in model.parameters() if p.requires_grad]
    device = params[0].device if params else torch.device("cpu")
    cuda = [device.index or 0] if device.type == "cuda" else []
    caught: list[warnings.WarningMessage] = []
    try:
        with torch.random.fork_rng(devices=cuda), warnings.catch_warnings(record=True) as recorded:
            warnings.simplefilter("always")
            caught = recorded
            with torch.autograd.detect_anomaly(check_nan=True):
                loss = rerun()
                report.loss_finite = bool(torch.isfinite(loss.detach()).all())
                torch.autograd.grad(loss, params, allow_unused=True)
    except Exception as err:  # a diagnosis must not end the run itself (a compiled region, memory, ...)
        found = re.search(r"Function '(\w+)' returned nan", str(err))
        if found:
            report.operation = found.group(1)
        else:
            report.error = f"{type(err).__name__}: {err}"
    finally:
        for handle in handles:
            handle.remove()
    for w in caught:
        message = str(w.message)
        if "Traceback of forward call" in message:
            report.traceback = message
            report.source = _innermost_project_frame(message)
    return report


def _all_finite(value) -> bool:
    """True when every floating tensor in ``value`` (tensors, sequences, dicts, dataclasses) is finite."""
    if isinstance(value, Tensor):
        return not value.is_floating_point() or bool(torch.isfinite(value.detach()).all())
    if isinstance(value, (list, tuple)):
        return all(_all_finite(v) for v in value)
    if isinstance(value, dict):
        return all(_all_finite(v) for v in value.values())
    if is_dataclass(value) and not isinstance(value, type):
        return all(_all_finite(getattr(value, f.name)) for f in fields(value))
    return True


def _innermost_project_frame(traceback: str) -> str | None:
    """The last frame outside torch's own files: ``path:line (function): code``."""
    frames = [m for m in _FRAME.finditer(traceback) if "/torch/" not in m["file"]]
    if not frames:
        return None
    m = frames[-1]
    return f"{m['file']}:{m['line']} ({m['func']}): {m['code'].strip()}"
