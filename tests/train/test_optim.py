"""Optimizer groups, the warm-up + cosine schedule and the non-finite step guard."""

import math

import pytest
import torch
from torch import nn

from aesplat.model import build_model
from aesplat.train.optim import (
    OptimConfig,
    WarmupCosine,
    build_optimizer,
    build_param_groups,
    clip_and_check,
    current_learning_rates,
    resolve_impl,
    skipped_when,
)

IMPLS = ("for_loop", "foreach", "fused")


@pytest.fixture(scope="module")
def tiny_model():
    return build_model(size="tiny", appearance="full", sh_degree=2)


def test_groups_cover_every_trainable_parameter_once(tiny_model):
    groups = build_param_groups(tiny_model.named_parameter_groups(), OptimConfig(), pretrained_backbone=False)
    ids = [id(p) for g in groups for p in g["params"]]
    trainable = {id(p) for p in tiny_model.parameters() if p.requires_grad}
    assert len(ids) == len(set(ids)), "a parameter is in two optimizer groups"
    assert set(ids) == trainable
    names = {g["name"] for g in groups}
    assert {"appearance", "rest", "backbone"} <= names


def test_group_learning_rates_and_decay(tiny_model):
    cfg = OptimConfig(lr=1e-4, appearance_lr=3e-4, backbone_lr_scale=0.1)
    groups = tiny_model.named_parameter_groups()
    opt, _ = build_optimizer(groups, cfg, pretrained_backbone=False, total_steps=10)
    assert tiny_model.pretrained_backbone is False
    for g in opt.param_groups:
        want = {"appearance": 3e-4, "rest": 1e-4, "backbone": 1e-4}[g["name"]]
        assert g["initial_lr"] == pytest.approx(want)
        assert g["weight_decay"] == (0.05 if g["decay"] else 0.0)
        if not g["decay"]:
            continue
        assert all(p.ndim >= 2 for p in g["params"])
    assert opt.defaults["betas"] == (0.9, 0.95)
    # A pretrained backbone trains at a tenth of the base rate.
    opt, _ = build_optimizer(tiny_model.named_parameter_groups(), cfg, pretrained_backbone=True, total_steps=10)
    assert [g["initial_lr"] for g in opt.param_groups if g["name"] == "backbone"] == pytest.approx([1e-5, 1e-5])


def test_no_decay_for_norms_biases_tokens(tiny_model):
    groups = build_param_groups(tiny_model.named_parameter_groups(), OptimConfig(), pretrained_backbone=False)
    no_decay = {id(p) for g in groups if not g["decay"] for p in g["params"]}
    named = dict(tiny_model.named_parameters())
    checked = 0
    for name, p in named.items():
        if p.requires_grad and (name.endswith("bias") or "norm" in name.lower() or "token" in name.lower()):
            assert id(p) in no_decay, name
            checked += "token" in name.lower()
    assert checked >= 3  # the camera and register tokens of the trunk, the camera head's empty pose token


def test_duplicate_parameter_is_an_error():
    layer = nn.Linear(2, 2)
    groups = {"rest": [("w", layer.weight)], "appearance": [("w", layer.weight)]}
    with pytest.raises(ValueError, match="also in"):
        build_param_groups(groups, OptimConfig(), pretrained_backbone=False)


def test_warmup_then_cosine():
    sched = WarmupCosine(warmup_steps=10, total_steps=110, min_ratio=0.1)
    assert sched(0) == pytest.approx(0.1)
    assert sched(9) == pytest.approx(1.0)
    assert sched(10) == pytest.approx(1.0)
    assert sched(60) == pytest.approx(0.1 + 0.9 * 0.5)
    assert sched(110) == pytest.approx(0.1)
    assert sched(10_000) == pytest.approx(0.1)
    values = [sched(s) for s in range(10, 111)]
    assert all(a >= b for a, b in zip(values, values[1:]))


def test_scheduler_steps_every_group_and_reports_names():
    layer_a, layer_b = nn.Linear(3, 3), nn.Linear(3, 3)
    named = {"appearance": list(layer_a.named_parameters()), "rest": list(layer_b.named_parameters())}
    cfg = OptimConfig(warmup_steps=4)
    opt, sched = build_optimizer(named, cfg, pretrained_backbone=False, total_steps=20)
    for _ in range(4):
        opt.step()
        sched.step()
    lrs = current_learning_rates(opt)
    assert lrs["appearance"] == pytest.approx(3e-4)
    assert lrs["rest"] == pytest.approx(1e-4)


def _adam_snapshot(opt):
    return {id(p): {k: v.clone() for k, v in s.items()} for p, s in opt.state.items()}


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("poison", ["gradient", "loss"])
def test_non_finite_step_leaves_params_and_adam_state_bit_identical(poison, impl):
    model = nn.Sequential(nn.Linear(4, 8), nn.LayerNorm(8), nn.Linear(8, 1))
    named = {"rest": list(model.named_parameters())}
    opt, _ = build_optimizer(named, OptimConfig(impl=impl), pretrained_backbone=False, total_steps=10)
    assert bool(opt.defaults["fused"]) == (impl == "fused")
    assert bool(opt.defaults["foreach"]) == (impl == "foreach")
    x = torch.randn(5, 4)
    model(x).pow(2).mean().backward()
    opt.step()  # Adam state exists
    params = [p.detach().clone() for p in model.parameters()]
    state = _adam_snapshot(opt)

    opt.zero_grad(set_to_none=True)
    loss = model(x).pow(2).mean()
    if poison == "loss":
        loss = loss * float("nan")
    loss.backward()
    if poison == "gradient":
        model[0].weight.grad[0, 0] = float("inf")
    norm, found_inf = clip_and_check(model.parameters(), 0.5, loss)
    assert found_inf.item() == 1.0 and found_inf.dtype == torch.float32 and not math.isfinite(norm.item())
    with skipped_when(opt, found_inf):
        opt.step()
    assert not hasattr(opt, "found_inf"), "a later step must not see this step's flag"
    for before, after in zip(params, model.parameters()):
        assert torch.equal(before, after)
    after_state = _adam_snapshot(opt)
    for pid, entries in state.items():
        for k, v in entries.items():
            assert torch.equal(v, after_state[pid][k]), k


def test_clip_reports_the_unclipped_norm():
    p = nn.Parameter(torch.zeros(4))
    p.grad = torch.full((4,), 2.0)
    norm, found_inf = clip_and_check([p], 0.5, torch.tensor(1.0))
    assert found_inf.item() == 0.0 and norm.item() == pytest.approx(4.0)
    assert p.grad.norm().item() == pytest.approx(0.5, rel=1e-4)


def _train_with_a_skipped_step(impl: str):
    """Five steps of a small two-group model, the third skipped (NaN gradient): parameters and AdamW state."""
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(4, 8), nn.LayerNorm(8), nn.Linear(8, 2))
    named = {"rest": list(model[:2].named_parameters()), "appearance": list(model[2].named_parameters())}
    cfg = OptimConfig(impl=impl, warmup_steps=2)
    opt, sched = build_optimizer(named, cfg, pretrained_backbone=False, total_steps=5)
    gen = torch.Generator().manual_seed(1)
    for step in range(5):
        opt.zero_grad(set_to_none=True)
        loss = model(torch.randn(6, 4, generator=gen)).pow(2).mean()
        loss.backward()
        if step == 2:
            model[0].weight.grad[1, 1] = float("nan")
        _, found_inf = clip_and_check(model.parameters(), 0.5, loss)
        assert found_inf.item() == (step == 2)
        with skipped_when(opt, found_inf):
            opt.step()
        sched.step()
    return [p.detach().clone() for p in model.parameters()], _adam_snapshot(opt).values()


@pytest.mark.parametrize("impl", ["foreach", "fused"])
def test_fast_kernels_make_the_for_loop_updates(impl):
    params_ref, state_ref = _train_with_a_skipped_step("for_loop")
    params, state = _train_with_a_skipped_step(impl)
    for a, b in zip(params_ref, params):
        torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-7)
    for ref, got in zip(state_ref, state):
        assert float(got["step"]) == float(ref["step"]) == 4.0  # 5 batches, one skipped
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(got[key], ref[key], rtol=1e-6, atol=1e-10)


def test_auto_impl_is_fused_on_cpu_and_unknown_impl_is_an_error():
    assert resolve_impl("auto", [torch.zeros(2)]) == "fused"
    assert resolve_impl("for_loop", [torch.zeros(2)]) == "for_loop"
    assert resolve_impl("auto", [torch.zeros(2, device="meta")]) == "foreach"
    with pytest.raises(ValueError, match="optim.impl"):
        OptimConfig(impl="apex")


@pytest.mark.parametrize("impl", IMPLS)
def test_the_fused_kernel_skips_without_reading_the_flag_on_the_host(impl):
    """Fused AdamW takes the flag on the device; the other kernels read it (one synchronisation on a GPU)."""
    from .host_syncs import HostSyncCounter

    model = nn.Linear(4, 2)
    opt, _ = build_optimizer({"rest": list(model.named_parameters())}, OptimConfig(impl=impl), False, 10)
    loss = model(torch.randn(3, 4)).pow(2).mean()
    loss.backward()
    with HostSyncCounter().count() as syncs:
        _, found_inf = clip_and_check(model.parameters(), 0.5, loss)
        with skipped_when(opt, found_inf):
            opt.step()
    assert len(syncs) == (0 if impl == "fused" else 1), syncs
    assert float(opt.state[model.weight]["step"]) == 1.0  # a finite step is taken
