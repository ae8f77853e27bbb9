"""CPU (gloo) DDP through the real entry point: a 2-process fit whose ranks see different data, and a test
whose ranks, started apart, write one evaluation folder."""

import json
import os
import socket
import subprocess
import sys

import torch

from tests.helpers import REPO


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


def test_ranks_started_apart_write_one_evaluation_folder(smoke_shards, tmp_path):
    """torchrun starts every rank itself, so each names the evaluation folder from its own clock. Rank 1 is
    given another name here (as a clock a second later would): every render still lands in rank 0's folder."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run_dir = tmp_path / "run"
    command = [sys.executable, "-m", "aesplat.cli", "test", "-c", "conf/smoke.yaml",
               "--data.root", str(smoke_shards), "--trainer.default_root_dir", str(run_dir),
               "--trainer.strategy", "ddp", "--trainer.devices", "2",
               "--trainer.enable_progress_bar", "false"]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "AESPLAT_EVALUATION_DIR"}
    env.update(WANDB_MODE="disabled", PYTHONPATH=str(REPO), OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1",
               MASTER_PORT=str(port), WORLD_SIZE="2", LOCAL_WORLD_SIZE="2", GROUP_RANK="0",
               TORCHELASTIC_RUN_ID="evaluation-folder")  # fmt: skip
    elsewhere = run_dir / "test-rank1-clock"
    procs = [
        subprocess.Popen(
            command,
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={
                **env,
                "RANK": str(rank),
                "LOCAL_RANK": str(rank),
                **({"AESPLAT_EVALUATION_DIR": str(elsewhere)} if rank else {}),
            },
        )  # fmt: skip
        for rank in (0, 1)
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=420)
        assert proc.returncode == 0, err[-6000:]

    folders = sorted(p.name for p in run_dir.iterdir() if p.is_dir() and not p.is_symlink())
    assert len(folders) == 1 and folders[0].startswith("test-20"), folders
    out = run_dir / folders[0]
    assert len(list((out / "renders").glob("*.png"))) == 2, "one render from each rank"
    assert (out / "summary.json").exists() and not elsewhere.exists()
