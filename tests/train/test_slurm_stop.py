"""slurm/train.sbatch cancelled on a real SLURM cluster (slurm/local_cluster.sh, CPU): `scancel`, like a time
limit without a requeue, sends SIGTERM to every process of the job. Skipped when no cluster answers, except in
CI (CI=true), where that is a failure (as in tests/train/test_slurm_jobs.py).
"""

import subprocess

import pytest

from tests.train.slurm_cluster import (
    CPU_JOB,
    FINAL_STATES,
    STEPS,
    job_info,
    sbatch,
    wait_for_end,
    wait_until,
    weights,
)

pytestmark = pytest.mark.slurm


def test_a_cancelled_job_saves_where_it_stopped(job_env, smoke_shards, tmp_path):
    """`scancel` sends SIGTERM to every process of the job, the data-loader workers and wandb's service
    included: the step under way finishes on both ranks, last.ckpt is saved at that step and the fit says so.
    The job holds in step 2 (tests.train.helpers.HoldUntilStopSignal) until it has the signal."""
    run_dir, ready, log = tmp_path / "run", tmp_path / "ready", tmp_path / "job.out"
    overlay = tmp_path / "hold.yaml"
    overlay.write_text(
        "trainer:\n  callbacks:\n    - class_path: tests.train.helpers.HoldUntilStopSignal\n"
        f"      init_args:\n        ready: {ready}\n        at: 1\n"
    )
    # One data-loader worker per rank: with more, a rank would get none of the smoke data's two validation
    # scenes. An offline wandb run: wandb's service process is one of the job's processes too, and SIGTERM
    # ends it; the fit must save all the same.
    args = ["-c", "conf/smoke.yaml", "-c", str(overlay), "--data.root", str(smoke_shards),
            "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(STEPS),
            "--last_checkpoint.every_n_train_steps", str(STEPS), "--data.num_workers", "1",
            "--trainer.logger", "true", "--wandb.mode", "offline", "--trainer.enable_progress_bar",
            "false"]  # fmt: skip
    job_id = sbatch(job_env, "train.sbatch", CPU_JOB, args, log, "cancelled")
    wait_until(lambda: ready.exists() or job_info(job_env, job_id)["JobState"] in FINAL_STATES, "step 2")
    assert job_info(job_env, job_id)["JobState"] == "RUNNING", log.read_text()
    subprocess.run(["scancel", job_id], env=job_env, check=True)
    info = wait_for_end(job_env, job_id, log)
    last = run_dir / "checkpoints" / "last.ckpt"
    assert info["JobState"] == "CANCELLED", info
    assert f"aesplat fit: stopped by SIGTERM after step 2; saved {last}" in info["log"], info["log"][-6000:]
    assert "killed by signal" not in info["log"], info["log"][-6000:]
    assert weights(last)["global_step"] == 2
