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

REPO = Path(__file__).resolve().parents[2]


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
    assert "parameter(s) had non-finite gradients (encoder." in report


def test_fit_with_one_nan_step_skips_it_and_carries_on(smoke_shards, tmp_path, monkeypatch):
    # The first training step's render and its anomaly re-run (the second call) are poisoned.
    poison_renders(monkeypatch, poisoned_calls={1, 2})
    run_dir = tmp_path / "run"
    cli.main(_fit_args(smoke_shards, run_dir, max_steps=4))
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 4 and ckpt["skipped_steps"] == 1
    assert ckpt["skip_guard"]["recent"] == [True, False, False, False]
    assert "NaNGradientBackward" in ckpt["skip_guard"]["first_report"]
    assert (run_dir / "nonfinite_step0.txt").is_file()
