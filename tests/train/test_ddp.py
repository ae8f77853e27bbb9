"""A 2-process CPU (gloo) DDP fit through the real entry point: it finishes and the ranks see different data."""

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]


def test_ddp_two_processes_on_cpu(smoke_shards, tmp_path):
    record = tmp_path / "seen"
    overlay = tmp_path / "record.yaml"
    overlay.write_text(
        "trainer:\n  callbacks:\n    - class_path: tests.train.helpers.RecordTrainingScenes\n"
        f"      init_args:\n        out_dir: {record}\n"
    )
    run_dir = tmp_path / "run"
    command = [sys.executable, "-m", "aesplat.cli", "fit", "-c", "conf/smoke.yaml", "-c", str(overlay),
               "--data.root", str(smoke_shards), "--trainer.default_root_dir", str(run_dir),
               "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.max_steps", "3",
               "--data.train_batches_per_epoch", "3", "--last_checkpoint.every_n_train_steps", "3",
               "--trainer.enable_progress_bar", "false"]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=420)
    assert proc.returncode == 0, proc.stderr[-6000:]

    seen = {r: json.loads((record / f"rank{r}.json").read_text()) for r in (0, 1)}
    assert all(s["world_size"] == 2 for s in seen.values())
    assert all(len(s["seen"]) == 3 for s in seen.values()), "every rank runs the same number of steps"
    samples = [{tuple(map(str, x)) for x in s["seen"]} for s in seen.values()]
    assert samples[0].isdisjoint(samples[1]), f"ranks trained on the same samples: {samples}"
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 3
