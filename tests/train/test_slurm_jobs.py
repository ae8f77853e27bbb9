"""slurm/train.sbatch and slurm/eval.sbatch submitted to a real SLURM cluster (slurm/local_cluster.sh, CPU).

Two ranks train under Lightning's SLURM environment on different data; a job preempted the way SLURM does it
(SIGUSR1 to its tasks) writes the HPC checkpoint, is requeued and ends with the parameters of an uninterrupted
job; the evaluation job writes its tables; a job whose tasks and GPUs per node differ stops at once.
Skipped when no cluster answers, except in CI (CI=true), where that is a failure.
"""

import csv
import json
import subprocess
import time
from pathlib import Path

import pytest
import torch

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

PREEMPT_AT = 2  # the preempted job holds before this step (after last.ckpt of step 2) until it is signalled

pytestmark = pytest.mark.slurm


def fit_args(shards: Path, run_dir: Path, record: Path, tmp_path: Path, hold_at: int | None = None) -> list:
    """``aesplat fit`` arguments of a training job; ``hold_at``: the job waits before that step until it has
    the requeue signal (tests.train.helpers.HoldUntilRequeueSignal), so it is still running when signalled."""
    overlay = tmp_path / "record.yaml"
    hold = ""
    if hold_at is not None:
        hold = (
            "    - class_path: tests.train.helpers.HoldUntilRequeueSignal\n"
            f"      init_args:\n        at: {hold_at}\n"
        )
    overlay.write_text(
        "trainer:\n  callbacks:\n    - class_path: tests.train.helpers.RecordTrainingScenes\n"
        f"      init_args:\n        out_dir: {record}\n{hold}"
    )
    return ["-c", "conf/smoke.yaml", "-c", str(overlay), "--data.root", str(shards),
            "--trainer.default_root_dir", str(run_dir), "--trainer.max_steps", str(STEPS),
            "--data.train_batches_per_epoch", str(STEPS), "--last_checkpoint.every_n_train_steps", "2",
            "--trainer.enable_progress_bar", "false"]  # fmt: skip


def records(folder: Path) -> list[dict]:
    return [json.loads((folder / f"rank{r}.json").read_text()) for r in (0, 1)]


def wandb_run_ids(run_dir: Path) -> list[str]:
    """The run id of every offline wandb run in the run directory (``wandb/offline-run-<time>-<id>``)."""
    return sorted(p.name.rsplit("-", 1)[1] for p in (run_dir / "wandb").glob("offline-run-*"))


@pytest.fixture(scope="module")
def uninterrupted(job_env, smoke_shards, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("slurm_uninterrupted")
    run_dir, record, log = tmp / "run", tmp / "record", tmp / "job.out"
    started = time.monotonic()
    args = fit_args(smoke_shards, run_dir, record, tmp)
    job_id = sbatch(job_env, "train.sbatch", CPU_JOB, args, log, "uninterrupted")
    info = wait_for_end(job_env, job_id, log)
    info["seconds"] = time.monotonic() - started
    return info, run_dir, record


@pytest.fixture(scope="module")
def preempted(job_env, smoke_shards, uninterrupted, tmp_path_factory):
    """The same job, sent SIGUSR1 (as SLURM does before the time limit) once it has saved step 2. It holds
    before step 3 until the signal is there, so it is always preempted while it runs: the requeue checkpoint
    is the state after step 3."""
    tmp = tmp_path_factory.mktemp("slurm_preempted")
    run_dir, record, log = tmp / "run", tmp / "record", tmp / "job.out"
    started = time.monotonic()
    args = fit_args(smoke_shards, run_dir, record, tmp, hold_at=PREEMPT_AT)
    job_id = sbatch(job_env, "train.sbatch", CPU_JOB, args, log, "preempted")
    last = run_dir / "checkpoints" / "last.ckpt"
    wait_until(lambda: last.exists() or job_info(job_env, job_id)["JobState"] in FINAL_STATES, "step 2")
    assert job_info(job_env, job_id)["JobState"] == "RUNNING", log.read_text()
    # What `#SBATCH --signal=SIGUSR1@90` does 90 s before the time limit: signal every task of the job.
    subprocess.run(["scancel", "--signal=USR1", job_id], env=job_env, check=True)
    info = wait_for_end(job_env, job_id, log)
    info["seconds"] = time.monotonic() - started
    return info, run_dir, record


def test_two_cpu_ranks_train_under_lightnings_slurm_environment(uninterrupted):
    info, run_dir, record = uninterrupted
    assert info["JobState"] == "COMPLETED", info["log"][-6000:]
    assert "1 node(s) x 2 CPU process(es)" in info["log"]
    ranks = records(record)
    for rank, seen in enumerate(ranks):
        assert (seen["world_size"], seen["slurm_procid"]) == (2, str(rank))
        assert seen["cluster_environment"] == "SLURMEnvironment"
        # srun started this process (no launcher of Lightning's spawned it)
        assert seen["processes_started_outside"] and seen["parent_process"] == "slurmstepd", seen
        assert len(seen["seen"]) == STEPS
    samples = [{json.dumps(x) for x in seen["seen"]} for seen in ranks]
    assert samples[0].isdisjoint(samples[1]), "both ranks trained on the same samples"
    assert weights(run_dir / "checkpoints" / "last.ckpt")["global_step"] == STEPS
    assert (run_dir / "config.yaml").exists()
    assert len(wandb_run_ids(run_dir)) == 1


def test_preempted_job_is_requeued_and_ends_as_if_uninterrupted(uninterrupted, preempted):
    info, run_dir, record = preempted
    assert info["JobState"] == "COMPLETED", info["log"][-6000:]
    assert info["Restarts"] == "1", info
    assert "(restart 0)" in info["log"] and "(restart 1)" in info["log"]

    hpc = sorted(run_dir.glob("hpc_ckpt_*.ckpt"))
    assert [p.name for p in hpc] == ["hpc_ckpt_1.ckpt"], info["log"][-6000:]
    stopped_at = weights(hpc[0])["global_step"]
    assert stopped_at == PREEMPT_AT + 1  # the step under way when the signal came
    assert f"resuming from {hpc[0]}" in info["log"]

    # The requeued job started at the checkpoint's step and saw exactly the batches the uninterrupted one saw
    # from there on, on both ranks: no step lost, none repeated.
    reference = records(uninterrupted[2])
    for rank, seen in enumerate(records(record)):
        assert seen["slurm_restart_count"] == "1"
        assert seen["first_step"] == stopped_at
        assert seen["seen"] == reference[rank]["seen"][stopped_at:]

    final, expected = (
        weights(run_dir / "checkpoints" / "last.ckpt"),
        weights(uninterrupted[1] / "checkpoints/last.ckpt"),
    )
    assert final["global_step"] == expected["global_step"] == STEPS
    for name, value in expected.items():
        if name != "global_step":
            torch.testing.assert_close(final[name], value, rtol=1e-5, atol=1e-6, msg=name)

    run_id = (run_dir / "wandb_run_id").read_text().strip()
    assert wandb_run_ids(run_dir) == [run_id, run_id], "the requeued job must continue the same wandb run"


def test_eval_job_writes_per_scene_csv_and_summary(job_env, smoke_shards, uninterrupted, tmp_path):
    _, run_dir, _ = uninterrupted
    log, out, ckpt = tmp_path / "eval.out", run_dir / "test-latest", run_dir / "checkpoints" / "last.ckpt"
    args = ["-c", "conf/smoke.yaml", "--data.root", str(smoke_shards), "--ckpt_path", str(ckpt),
            "--trainer.default_root_dir", str(run_dir), "--trainer.logger", "false",
            "--trainer.enable_progress_bar", "false"]  # fmt: skip
    job_id = sbatch(job_env, "eval.sbatch", ["--gpus-per-node=0", "--cpus-per-task=1"], args, log, "eval")
    info = wait_for_end(job_env, job_id, log)
    assert info["JobState"] == "COMPLETED", info["log"][-6000:]
    with open(out / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    summary = json.loads((out / "summary.json").read_text())
    assert len(rows) == summary["num_scenes"] == 2  # the smoke data's two test scenes
    assert all(float(r["psnr"]) > 0 for r in rows)
    mean = sum(float(r["psnr"]) for r in rows) / len(rows)
    assert summary["metrics"]["psnr"] == pytest.approx(mean)


def test_job_with_tasks_not_matching_gpus_fails_fast(job_env, tmp_path):
    log = tmp_path / "mismatch.out"
    env = {**job_env, "AESPLAT_SLURM_CPU": "0"}  # the GPU path: 2 GPU slots, 1 task
    options = ["--gpus-per-node=2", "--ntasks-per-node=1", "--cpus-per-task=1"]
    job_id = sbatch(env, "train.sbatch", options, ["-c", "conf/smoke.yaml"], log, "mismatch")
    info = wait_for_end(env, job_id, log)
    assert (info["JobState"], info["ExitCode"]) == ("FAILED", "2:0"), info
    assert "2 GPUs per node but 1 tasks per node" in info["log"]
    assert "(restart" not in info["log"], "it must stop before srun"
