"""Host synchronisations per training step of `aesplat fit`: none on an ordinary step, one on a step that logs.

Counted on the CPU by ``host_syncs.HostSyncCounter`` (what a GPU run of the same code would wait for). The
torch rasterizer's own reads (culling and tile sizes need counts on the host) are left out of its budget: on
a GPU the gsplat backend renders instead, and that backend is counted whole, with a stand-in for
``gsplat.rasterization`` (gsplat needs CUDA) that returns tensors of its outputs' shapes.
"""

import csv
from functools import partial
from types import SimpleNamespace

import torch

from aesplat import cli
from aesplat.render import interface
from aesplat.render.gsplat_backend import render_gsplat
from aesplat.render.settings import RenderSettings
from aesplat.types import Gaussians
from tests.helpers import REPO

from .host_syncs import HostSyncCounter

STEPS, LOG_EVERY = 3, 2


def test_the_counter_sees_what_would_wait_for_a_gpu():
    weight = torch.nn.Parameter(torch.randn(3))  # made before counting: a device tensor
    with HostSyncCounter().count() as syncs:
        total = (weight * 2).sum().detach()
        bool(total > 0), float(total), weight.nonzero(), weight[weight > 0]  # four reads of device values
        host = total.detach().cpu()  # a fifth; what comes from it is on the host
        float(host), host.tolist(), torch.tensor(1.0).item(), torch.zeros(2).sum().item()
    assert [s.split(" at ")[0] for s in syncs] == ["item", "item", "nonzero", "boolean-mask indexing", ".cpu()"]
    assert all("test_host_syncs.py" in s for s in syncs)


def _fit(shards, run_dir, *extra: str) -> HostSyncCounter:
    cli.main(["fit", "-c", str(REPO / "conf" / "smoke.yaml"), "--data.root", str(shards),
              "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(STEPS),
              "--data.train_batches_per_epoch", str(STEPS), "--trainer.limit_val_batches", "0",
              "--trainer.log_every_n_steps", str(LOG_EVERY), "--throughput.window", str(LOG_EVERY),
              "--trainer.logger+=CSVLogger", "--trainer.logger.save_dir", str(run_dir),
              "--model.eval.log_images_every_n_steps", "0", "--checkpoint.save_top_k", "0",
              "--last_checkpoint.save_last", "false", "--trainer.enable_progress_bar", "true",
              "--trainer.profiler", "tests.train.host_syncs.HostSyncCounter", *extra])  # fmt: skip
    counter = HostSyncCounter.last
    assert len(counter.steps) == STEPS
    return counter


def _assert_one_read_per_logging_step(steps: list[list[str]]) -> None:
    for i, syncs in enumerate(steps):
        if (i + 1) % LOG_EVERY:
            assert syncs == [], f"step {i} (no logging) waits for the device: {syncs}"
        else:  # the logged scalars and the skip flags, in one transfer
            assert len(syncs) == 1 and syncs[0].startswith(".cpu() at train/module.py"), f"step {i}: {syncs}"


def test_a_training_step_waits_for_the_device_only_when_it_logs(smoke_shards, tmp_path):
    run_dir = tmp_path / "run"
    counter = _fit(smoke_shards, run_dir)
    assert all(any("render/" in s for s in step) for step in counter.steps), (
        "the counter saw no rasterizer read"
    )
    _assert_one_read_per_logging_step([[s for s in step if "render/" not in s] for step in counter.steps])
    # The logs are still written every LOG_EVERY steps: training scalars, skip count, speed.
    with next(run_dir.rglob("metrics.csv")).open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/loss")]
    assert [int(r["step"]) for r in rows] == list(range(LOG_EVERY - 1, STEPS, LOG_EVERY))
    assert all(float(r["train/skipped_steps"]) == 0 and float(r["train/sec_per_step"]) > 0 for r in rows)


def _stand_in_gsplat(calls: list[tuple[int, int]]) -> SimpleNamespace:
    """A ``gsplat`` module whose ``rasterization`` returns colour+depth [B, V, H, W, 4] and alpha
    [B, V, H, W, 1] computed from every tensor it is given (so the backward reaches them all), reading none."""

    def rasterization(
        *, means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, **kw
    ):
        b, v = viewmats.shape[:2]
        calls.append((b, v))
        level = sum(t.mean() for t in (means, quats, scales, opacities, colors, viewmats, Ks))
        value = torch.sigmoid(level + backgrounds.mean(-1))[..., None, None, None]  # [B, V, 1, 1, 1]
        return value.expand(b, v, height, width, 4), value.expand(b, v, height, width, 1), {}

    return SimpleNamespace(rasterization=rasterization)


def test_the_gsplat_backend_reads_nothing_unless_its_count_is_asked_for():
    calls = []
    g = Gaussians(torch.randn(2, 50, 3) + torch.tensor([0.0, 0.0, 3.0]), torch.randn(2, 50, 4),
                  torch.rand(2, 50, 3) * 0.1, torch.rand(2, 50), torch.randn(2, 50, 4, 3))  # fmt: skip
    g.opacities[:, :10] = 0.0  # ten transparent Gaussians per scene
    ext = torch.eye(4).expand(2, 3, 4, 4)
    intr = torch.tensor([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]).expand(2, 3, 3, 3)
    counter = HostSyncCounter()
    with counter.count() as syncs:
        out, stats = render_gsplat(g, ext, intr, 8, 6, torch.zeros(2, 3), 1, RenderSettings(),
                                   gsplat=_stand_in_gsplat(calls))  # fmt: skip
    assert calls == [(2, 3)] and out.color.shape == (2, 3, 3, 8, 6) and out.alpha.shape == (2, 3, 1, 8, 6)
    assert syncs == []
    with counter.count() as syncs:
        assert stats.culled_transparent == 2 * 3 * 10 and int(stats.culled_transparent) == 60  # read once
    assert [s.split(" at ")[0] for s in syncs] == ["item"] and "render/gsplat_backend.py" in syncs[0]


def test_a_training_step_with_the_gsplat_backend_never_waits(smoke_shards, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setitem(interface.BACKENDS, "gsplat", partial(render_gsplat, gsplat=_stand_in_gsplat(calls)))
    counter = _fit(smoke_shards, tmp_path / "run", "--model.render.backend", "gsplat")
    assert len(calls) >= STEPS, "the stand-in rasterizer was not called"
    _assert_one_read_per_logging_step(counter.steps)  # the rasterizer's reads included
