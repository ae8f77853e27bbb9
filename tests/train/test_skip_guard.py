"""The non-finite step guard: rare skips pass, persistent ones stop the run, the first one is explained."""

from pathlib import Path

import pytest
import torch

from aesplat import cli
from aesplat.render import render as real_render
from aesplat.train import module
from aesplat.train.optim import OptimConfig
from aesplat.train.skip_guard import PersistentNonFiniteSteps, SkipGuard, explain_non_finite_step
from aesplat.types import RenderOutput
from tests.helpers import REPO


class NaNGradient(torch.autograd.Function):
    """Identity forward, NaN backward: a finite loss with non-finite gradients (as a singular sqrt gives)."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return torch.full_like(grad, float("nan"))


def record(guard: SkipGuard, pattern: str, start: int = 0) -> None:
    """Feed steps: 's' skipped, '.' normal."""
    for i, c in enumerate(pattern):
        guard.record(start + i, c == "s")


def test_rare_skips_pass_and_are_counted():
    guard = SkipGuard(OptimConfig())
    record(guard, ("s" + "." * 9) * 30)  # 10 % of every window, never two in a row
    assert sum(guard.recent) == 10 and guard.consecutive == 0
    guard = SkipGuard(OptimConfig(max_skipped_fraction=1.0))
    record(guard, "s" * 9 + ".")  # nine in a row is still allowed
    assert guard.consecutive == 0


def test_ten_in_a_row_stop_the_run():
    guard = SkipGuard(OptimConfig())
    record(guard, "." * 50 + "s" * 9)
    with pytest.raises(PersistentNonFiniteSteps, match=r"step 59: 10 steps in a row were skipped"):
        guard.record(59, True)


def test_more_than_a_tenth_of_the_window_stops_the_run():
    guard = SkipGuard(OptimConfig())
    record(guard, "s.." * 10 + "." * 60)  # 10 of the last 90: allowed
    with pytest.raises(PersistentNonFiniteSteps, match=r"11 of the last 91 steps.*max_skipped_fraction"):
        guard.record(90, True)
    # Skips that have left the window no longer count.
    guard = SkipGuard(OptimConfig(skip_window=20, max_skipped_fraction=0.25))
    record(guard, "s." * 5 + "." * 15 + "s." * 5)


def test_limits_are_configurable_and_can_be_disabled():
    record(SkipGuard(OptimConfig(max_skipped_fraction=0, max_consecutive_skips=0)), "s" * 300)
    with pytest.raises(PersistentNonFiniteSteps, match="3 steps in a row"):
        record(SkipGuard(OptimConfig(max_consecutive_skips=3)), "sss")
    with pytest.raises(ValueError, match="skip_window >= 1"):
        SkipGuard(OptimConfig(skip_window=0))


def test_state_survives_a_checkpoint():
    guard = SkipGuard(OptimConfig(skip_window=10, max_skipped_fraction=1.0))
    record(guard, "..s.ss")
    guard.total = 3
    guard.first_report = "first skipped step 2: ..."
    state = guard.state_dict()
    assert all(isinstance(v, (list, int, str)) for v in state.values())  # loads with weights_only=True
    resumed = SkipGuard(OptimConfig(skip_window=10, max_skipped_fraction=1.0))
    resumed.load_state_dict(state)
    assert resumed.state_dict() == state
    # The resumed run continues the same window and streak: 2 in a row before, 8 more make 10.
    with pytest.raises(PersistentNonFiniteSteps, match="10 steps in a row"):
        record(resumed, "s" * 8, start=6)


def test_anomaly_report_names_the_operation_and_its_source_line():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 1))
    x = torch.randn(2, 3)

    def step_loss():
        hidden = NaNGradient.apply(model[0](x))  # the culprit
        return model[1](hidden).sum()

    report = explain_non_finite_step(7, model, step_loss, ["0.weight", "0.bias"], 2)
    assert report.operation == "NaNGradientBackward" and report.loss_finite and report.forward_module is None
    assert (
        report.source.startswith(f"{__file__}:") and "hidden = NaNGradient.apply(model[0](x))" in report.source
    )
    assert all(p.grad is None for p in model.parameters()), "the re-run must not accumulate gradients"
    text = report.summary()
    assert "first skipped step 7" in text and "NaNGradientBackward" in text and "0.weight, 0.bias" in text


def test_anomaly_report_finds_the_first_module_with_a_non_finite_output():
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.ReLU(), torch.nn.Linear(4, 1))
    with torch.no_grad():
        model[0].bias[1] = float("inf")
    report = explain_non_finite_step(0, model, lambda: model(torch.ones(2, 3)).sum(), [], 0)
    assert report.forward_module == "0" and not report.loss_finite
    assert "forward output of module '0' not finite" in report.summary()


def _flag(value: float) -> torch.Tensor:
    return torch.tensor(value)


def test_deferred_flags_count_exactly_and_stop_at_the_read_naming_the_step():
    """Flags read on the host some steps late (with the logs): the same counts and the same limit, and the
    message names the step that crossed it and the step that read it."""
    model = torch.nn.Linear(2, 1)
    sgd = torch.optim.SGD(model.parameters())
    guard = SkipGuard(OptimConfig(max_consecutive_skips=3, anomaly_report=False))
    for step, flag in enumerate([0.0, 1.0, 0.0]):
        guard.defer(step, _flag(flag))
    assert guard.total == 0 and len(guard.pending_flags()) == 3  # nothing is known before the read
    guard.resolve([f.item() for f in guard.pending_flags()], model, sgd, ".", current_step=2)
    assert guard.total == 1 and list(guard.recent) == [False, True, False] and guard.pending == []
    for step in range(3, 9):
        guard.defer(step, _flag(1.0))
    with pytest.raises(PersistentNonFiniteSteps, match=r"stopped at step 5: 3 steps in a row.*read at step 8"):
        guard.resolve([1.0] * 6, model, sgd, ".", current_step=8)
    with pytest.raises(ValueError, match="2 deferred steps but 1 flags"):
        guard.defer(9, _flag(0.0)), guard.defer(10, _flag(0.0)), guard.resolve([0.0], model, sgd, ".")


def test_a_skip_read_late_is_explained_with_its_own_batch(tmp_path):
    """The first skipped step is re-run with its own batch when it is read; its gradients are gone by then."""
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    batches = {0: torch.ones(2, 3), 1: torch.full((2, 3), float("nan"))}
    guard = SkipGuard(OptimConfig())
    for step, x in batches.items():
        guard.defer(step, _flag(float(step == 1)), lambda x=x: model(x).sum())
    with pytest.warns(UserWarning, match="non-finite training step explained"):
        guard.resolve([0.0, 1.0], model, torch.optim.SGD(model.parameters()), tmp_path, current_step=3)
    assert guard.total == 1 and "AddmmBackward0" in guard.first_report  # step 0's batch would be finite
    assert "gradients were gone" in guard.first_report and (tmp_path / "nonfinite_step1.txt").is_file()
    guard.defer(4, _flag(1.0), lambda: model(batches[1]).sum())
    assert guard.pending[-1][2] is None, "only the first skip is explained: no later batch is kept"


def _fit_args(shards, run_dir: Path, max_steps: int) -> list[str]:
    """conf/smoke.yaml on the CPU, no logger, no validation, one epoch, last.ckpt at the end."""
    return ["fit", "-c", str(REPO / "conf" / "smoke.yaml"), "--data.root", str(shards),
            "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(max_steps),
            "--trainer.logger", "false", "--trainer.limit_val_batches", "0", "--trainer.enable_progress_bar",
            "false", "--data.train_batches_per_epoch", str(max_steps),
            "--last_checkpoint.every_n_train_steps", str(max_steps)]  # fmt: skip


def poison_renders(monkeypatch, poisoned_calls) -> None:
    """Make the module's renders pass through ``NaNGradient`` on the given (1-based) calls of ``render``."""
    calls = {"n": 0}

    def render(*args, **kwargs):
        calls["n"] += 1
        out = real_render(*args, **kwargs)
        if calls["n"] in poisoned_calls:
            out = RenderOutput(NaNGradient.apply(out.color), out.depth, out.alpha)  # finite image, NaN gradient
        return out

    monkeypatch.setattr(module, "render", render)


def test_fit_with_a_persistent_nan_gradient_stops_and_names_the_operation(smoke_shards, tmp_path, monkeypatch):
    """`aesplat fit` (the real entry point, smoke config on the CPU) with a NaN gradient in every step."""
    poison_renders(monkeypatch, poisoned_calls=range(1, 1000))
    run_dir = tmp_path / "run"
    with pytest.warns(UserWarning, match="non-finite training step explained"):
        with pytest.raises(PersistentNonFiniteSteps) as info:
            cli.main(
                [*_fit_args(smoke_shards, run_dir, max_steps=20), "--model.optim.max_consecutive_skips", "3"]
            )
    message = str(info.value)
    assert "training stopped at step 2: 3 steps in a row were skipped" in message
    assert "NaNGradientBackward" in message and "test_skip_guard.py" in message
    report = (run_dir / "nonfinite_step0.txt").read_text()
    assert "out = RenderOutput(NaNGradient.apply(out.color), out.depth, out.alpha)" in report
    assert "parameter(s) had non-finite gradients (aggregator." in report


@pytest.mark.parametrize("impl", ["auto", "for_loop"])  # fused (the skip decided on the device) | on the host
def test_fit_with_one_nan_step_skips_it_and_carries_on(smoke_shards, tmp_path, monkeypatch, impl):
    # The first training step's render and its anomaly re-run (the second call) are poisoned.
    poison_renders(monkeypatch, poisoned_calls={1, 2})
    run_dir = tmp_path / "run"
    cli.main([*_fit_args(smoke_shards, run_dir, max_steps=4), "--model.optim.impl", impl])
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 4 and ckpt["skipped_steps"] == 1
    assert ckpt["skip_guard"]["recent"] == [True, False, False, False]
    assert "NaNGradientBackward" in ckpt["skip_guard"]["first_report"]
    assert (run_dir / "nonfinite_step0.txt").is_file()
