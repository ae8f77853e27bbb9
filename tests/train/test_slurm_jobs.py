"""slurm/train.sbatch and slurm/eval.sbatch submitted to a real SLURM cluster (slurm/local_cluster.sh, CPU).

Two ranks train under Lightning's SLURM environment on different data; a job preempted the way SLURM does it
(SIGUSR1 to its tasks) writes the HPC checkpoint, is requeued and ends with the parameters of an uninterrupted
job; the same on two nodes (one task each): loss for loss the one-node job, and exact after a requeue; a job
that loses a node ends soon, saying which rank, with its last checkpoint intact; the evaluation job writes its
tables; a job whose tasks and GPUs per node differ stops at once. Skipped when no cluster answers, except in
CI (CI=true), where that is a failure.
"""

import csv
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

from tests.helpers import REPO
from tests.train.slurm_cluster import (
    CLUSTER_CONF,
    CPU_JOB,
    FINAL_STATES,
    STEPS,
    job_info,
    record_job,
    sbatch,
    wait_for_end,
    wait_until,
    weights,
)

PREEMPT_AT = 2  # the preempted job holds before this step (after last.ckpt of step 2) until it is signalled
TWO_NODES = ["--nodes=2", "--ntasks-per-node=1", "--gpus-per-node=0", "--cpus-per-task=1"]
LOSE_AT = 3  # the job that loses a node: every rank holds before this step until the node is gone

pytestmark = pytest.mark.slurm


def fit_args(shards: Path, run_dir: Path, record: Path, tmp_path: Path, hold_at: int | None = None,
             hold: str = "") -> list:  # fmt: skip
    """``aesplat fit`` arguments of a training job; ``hold_at``: the job waits before that step until it has
    the requeue signal (tests.train.helpers.HoldUntilRequeueSignal), so it is still running when signalled;
    ``hold``: more callbacks, as YAML list items."""
    overlay = tmp_path / "record.yaml"
    if hold_at is not None:
        hold += (
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


def run_job(job_env, shards: Path, tmp: Path, options: list[str], role: str):
    run_dir, record, log = tmp / "run", tmp / "record", tmp / "job.out"
    started = time.monotonic()
    job_id = sbatch(job_env, "train.sbatch", options, fit_args(shards, run_dir, record, tmp), log, role)
    info = wait_for_end(job_env, job_id, log)
    info["seconds"] = time.monotonic() - started
    return info, run_dir, record


def preempt_job(job_env, shards: Path, tmp: Path, options: list[str], role: str):
    """The job, sent SIGUSR1 (as SLURM does before the time limit) once it has saved step 2. It holds before
    step 3 until the signal is there, so it is always preempted while it runs: the requeue checkpoint is the
    state after step 3."""
    run_dir, record, log = tmp / "run", tmp / "record", tmp / "job.out"
    started = time.monotonic()
    args = fit_args(shards, run_dir, record, tmp, hold_at=PREEMPT_AT)
    job_id = sbatch(job_env, "train.sbatch", options, args, log, role)
    last = run_dir / "checkpoints" / "last.ckpt"
    wait_until(lambda: last.exists() or job_info(job_env, job_id)["JobState"] in FINAL_STATES, "step 2")
    assert job_info(job_env, job_id)["JobState"] == "RUNNING", log.read_text()
    # What `#SBATCH --signal=SIGUSR1@90` does 90 s before the time limit: signal every task of the job.
    subprocess.run(["scancel", "--signal=USR1", job_id], env=job_env, check=True)
    info = wait_for_end(job_env, job_id, log)
    info["seconds"] = time.monotonic() - started
    return info, run_dir, record


@pytest.fixture(scope="module")
def uninterrupted(job_env, smoke_shards, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("slurm_uninterrupted")
    return run_job(job_env, smoke_shards, tmp, CPU_JOB, "uninterrupted")


@pytest.fixture(scope="module")
def preempted(job_env, smoke_shards, uninterrupted, tmp_path_factory):
    return preempt_job(job_env, smoke_shards, tmp_path_factory.mktemp("slurm_preempted"), CPU_JOB, "preempted")


@pytest.fixture(scope="module")
def two_nodes(job_env, smoke_shards, uninterrupted, tmp_path_factory):
    return run_job(job_env, smoke_shards, tmp_path_factory.mktemp("slurm_two_nodes"), TWO_NODES, "two-nodes")


@pytest.fixture(scope="module")
def two_nodes_preempted(job_env, smoke_shards, two_nodes, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("slurm_two_nodes_preempted")
    return preempt_job(job_env, smoke_shards, tmp, TWO_NODES, "two-nodes-preempted")


def assert_same_parameters(final: dict, expected: dict) -> None:
    assert final["global_step"] == expected["global_step"] == STEPS
    for name, value in expected.items():
        if name != "global_step":
            torch.testing.assert_close(final[name], value, rtol=1e-5, atol=1e-6, msg=name)


def assert_resumed_exactly(info: dict, run_dir: Path, record: Path, reference: tuple) -> None:
    """A preempted job: requeued once, resumed at its HPC checkpoint's step, and from there every rank saw the
    batches, had the losses and ended with the parameters of the ``reference`` job that ran uninterrupted."""
    assert info["JobState"] == "COMPLETED", info["log"][-6000:]
    assert info["Restarts"] == "1", info
    assert "(restart 0)" in info["log"] and "(restart 1)" in info["log"]
    hpc = sorted(run_dir.glob("hpc_ckpt_*.ckpt"))
    assert [p.name for p in hpc] == ["hpc_ckpt_1.ckpt"], info["log"][-6000:]
    stopped_at = weights(hpc[0])["global_step"]
    assert stopped_at == PREEMPT_AT + 1  # the step under way when the signal came
    assert f"resuming from {hpc[0]}" in info["log"]
    # The requeued job started at the checkpoint's step and saw exactly the batches the uninterrupted one saw
    # from there on, on every rank: no step lost, none repeated.
    for rank, (seen, expected) in enumerate(zip(records(record), records(reference[2]), strict=True)):
        assert seen["slurm_restart_count"] == "1" and seen["first_step"] == stopped_at
        assert seen["seen"] == expected["seen"][stopped_at:]
        assert seen["losses"] == pytest.approx(expected["losses"][stopped_at:], rel=1e-5, abs=1e-7), rank
    assert_same_parameters(weights(run_dir / "checkpoints" / "last.ckpt"),
                           weights(reference[1] / "checkpoints" / "last.ckpt"))  # fmt: skip


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


@pytest.mark.slow  # `make test-slurm` runs it; in CI the two-node preempted job covers the requeue
def test_preempted_job_is_requeued_and_ends_as_if_uninterrupted(uninterrupted, preempted):
    info, run_dir, record = preempted
    assert_resumed_exactly(info, run_dir, record, uninterrupted)

    run_id = (run_dir / "wandb_run_id").read_text().strip()
    assert wandb_run_ids(run_dir) == [run_id, run_id], "the requeued job must continue the same wandb run"


def test_two_nodes_train_loss_for_loss_as_one_node_with_two_tasks(uninterrupted, two_nodes):
    """The job on two nodes with a task each (world size 2 across a node boundary, node ranks from SLURM) is,
    step by step, the job on one node with two tasks: the same samples, losses and final parameters."""
    info, run_dir, record = two_nodes
    assert info["JobState"] == "COMPLETED", info["log"][-6000:]
    assert "2 node(s) x 1 CPU process(es)" in info["log"]
    ranks, reference = records(record), records(uninterrupted[2])
    assert [(r["world_size"], r["node_rank"], r["slurm_procid"]) for r in ranks] == [(2, 0, "0"), (2, 1, "1")]
    assert len({r["node"] for r in ranks}) == 2 and len({r["node"] for r in reference}) == 1
    for rank, (seen, expected) in enumerate(zip(ranks, reference, strict=True)):
        assert seen["seen"] == expected["seen"]
        assert len(seen["losses"]) == STEPS
        assert seen["losses"] == pytest.approx(expected["losses"], rel=1e-5, abs=1e-7), rank
    assert_same_parameters(weights(run_dir / "checkpoints" / "last.ckpt"),
                           weights(uninterrupted[1] / "checkpoints" / "last.ckpt"))  # fmt: skip


def test_a_preempted_two_node_job_resumes_exactly(two_nodes, two_nodes_preempted):
    info, run_dir, record = two_nodes_preempted
    assert "2 node(s) x 1 CPU process(es)" in info["log"]
    assert_resumed_exactly(info, run_dir, record, two_nodes)
    run_id = (run_dir / "wandb_run_id").read_text().strip()
    assert wandb_run_ids(run_dir) == [run_id, run_id], "the requeued job must continue the same wandb run"


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (a rank's data-loader workers)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.parametrize("how", ["killed", "frozen"])
def test_a_lost_node_ends_the_job_saying_which_rank_with_last_ckpt_intact(job_env, smoke_shards, tmp_path, how):
    """Node 2 goes away between steps. ``killed``: its slurmd, the job's step daemon on it and rank 1 with its
    workers are killed, so rank 0's next collective fails at once. ``frozen``: rank 1 and its workers stop
    (SIGSTOP) with their connections open, as behind a dead switch, so rank 0's collective fails only after
    ``--distributed.timeout`` (30 s here; torch's default would wait 30 minutes). Either way the job ends well
    within two minutes, the fit's last line names rank 1 and its node, and last.ckpt (step 2) is as it was."""
    run_dir, record, log, ready, go = (tmp_path / n for n in ("run", "record", "job.out", "ready", "go"))
    hold = (
        "    - class_path: tests.train.helpers.HoldUntilFile\n"
        f"      init_args:\n        ready: {ready}\n        go: {go}\n        at: {LOSE_AT}\n"
    )
    args = [*fit_args(smoke_shards, run_dir, record, tmp_path, hold=hold), "--distributed.timeout", "30"]
    job_id = sbatch(job_env, "train.sbatch", [*TWO_NODES, "--no-requeue"], args, log, f"lost-node-{how}")
    held = [Path(f"{ready}.rank{r}") for r in (0, 1)]
    wait_until(lambda: all(p.exists() for p in held) or job_info(job_env, job_id)["JobState"] in FINAL_STATES,
               f"both ranks before step {LOSE_AT}")  # fmt: skip
    assert job_info(job_env, job_id)["JobState"] == "RUNNING", log.read_text()[-6000:]
    last = run_dir / "checkpoints" / "last.ckpt"
    saved = last.read_bytes()
    lost = json.loads(held[1].read_text())
    rank1 = [lost["pid"], *children(lost["pid"])]
    slurmd = CLUSTER_CONF.parent / "run" / f"slurmd-{lost['node']}.pid"
    try:
        if how == "killed":
            for pid in [int(slurmd.read_text()), lost["parent"], *rank1]:
                os.kill(pid, signal.SIGKILL)
        else:
            for pid in rank1:
                os.kill(pid, signal.SIGSTOP)
        started = time.monotonic()
        go.touch()
        info = wait_for_end(job_env, job_id, log, timeout=300)
        seconds = time.monotonic() - started
        record_job(f"lost-node-{how}", after_loss=seconds)
    finally:
        for pid in rank1 if how == "frozen" else []:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        restart = [str(REPO / "slurm" / "local_cluster.sh"), "start-node", lost["node"]]
        subprocess.run(restart, env={**job_env, "AESPLAT_SLURM_DIR": str(CLUSTER_CONF.parent)}, check=True)
    assert info["JobState"] in ("FAILED", "NODE_FAIL"), info
    assert seconds < 120, f"the job ended {seconds:.0f} s after the node was lost"
    if how == "frozen":
        assert seconds > 30, "the collective should have waited for --distributed.timeout"
    line = f"aesplat fit: rank 1 (node {lost['node']}) of 2 lost at step {LOSE_AT} (rank 0 saw: "
    assert line in info["log"], info["log"][-6000:]
    assert "resume with --ckpt_path last" in info["log"]
    assert last.read_bytes() == saved and weights(last)["global_step"] == 2


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
