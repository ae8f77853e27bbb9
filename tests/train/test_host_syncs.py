"""Host synchronisations per training step of `aesplat fit`: none on an ordinary step, one on a step that logs.

Counted on the CPU by ``host_syncs.HostSyncCounter`` (what a GPU run of the same code would wait for). The
torch rasterizer's own reads (culling and tile sizes need counts on the host) are left out of the budget: on
a GPU the gsplat backend renders instead.
"""

import csv

import torch

from aesplat import cli
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


def test_a_training_step_waits_for_the_device_only_when_it_logs(smoke_shards, tmp_path):
    run_dir = tmp_path / "run"
    cli.main(["fit", "-c", str(REPO / "conf" / "smoke.yaml"), "--data.root", str(smoke_shards),
              "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(STEPS),
              "--data.train_batches_per_epoch", str(STEPS), "--trainer.limit_val_batches", "0",
              "--trainer.log_every_n_steps", str(LOG_EVERY), "--throughput.window", str(LOG_EVERY),
              "--trainer.logger+=CSVLogger", "--trainer.logger.save_dir", str(run_dir),
              "--model.eval.log_images_every_n_steps", "0", "--checkpoint.save_top_k", "0",
              "--last_checkpoint.save_last", "false", "--trainer.enable_progress_bar", "true",
              "--trainer.profiler", "tests.train.host_syncs.HostSyncCounter"])  # fmt: skip
    counter = HostSyncCounter.last
    assert len(counter.steps) == STEPS
    assert all(any("render/" in s for s in step) for step in counter.steps), (
        "the counter saw no rasterizer read"
    )
    outside = [[s for s in step if "render/" not in s] for step in counter.steps]
    for i, syncs in enumerate(outside):
        if (i + 1) % LOG_EVERY:
            assert syncs == [], f"step {i} (no logging) waits for the device: {syncs}"
        else:  # the logged scalars and the skip flags, in one transfer
            assert len(syncs) == 1 and syncs[0].startswith(".cpu() at train/module.py"), f"step {i}: {syncs}"
    # The logs are still written every LOG_EVERY steps: training scalars, skip count, speed.
    with next(run_dir.rglob("metrics.csv")).open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/loss")]
    assert [int(r["step"]) for r in rows] == list(range(LOG_EVERY - 1, STEPS, LOG_EVERY))
    assert all(float(r["train/skipped_steps"]) == 0 and float(r["train/sec_per_step"]) > 0 for r in rows)
