"""Jobs on a real SLURM cluster (slurm/local_cluster.sh, CPU), for the `slurm` tests: submitting the shipped
sbatch scripts, reading a job's state and waiting for it to end."""

import json
import os
import re
import subprocess
import time
from pathlib import Path

import torch

from tests.helpers import REPO

SLURM = REPO / "slurm"
CLUSTER_CONF = Path(os.environ.get("AESPLAT_SLURM_DIR", "/tmp/aesplat-slurm")) / "slurm.conf"
STEPS = 6  # per training job; last.ckpt every 2 steps
CPU_JOB = ["--gpus-per-node=0", "--ntasks-per-node=2", "--cpus-per-task=1"]
FINAL_STATES = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "BOOT_FAIL"}
# A file to which every submission appends {"role": ..., "job_id": ...} as a line of JSON, when set:
# scripts/slurm_jobs.py learns from it which job was which (it reads their times from slurmctld's log).
RECORD_JOBS = os.environ.get("AESPLAT_SLURM_RECORD_JOBS")


def sbatch(env: dict, script: str, options: list[str], args: list[str], log: Path, role: str) -> str:
    """Submit ``slurm/<script>`` from the repository root; returns the job id. ``role``: what the job is
    for (uninterrupted, preempted, two-nodes, ..., eval, mismatch), recorded with its id when
    AESPLAT_SLURM_RECORD_JOBS asks."""
    command = ["sbatch", "--parsable", f"--output={log}", *options, str(SLURM / script), *args]
    proc = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    job_id = proc.stdout.strip().split(";")[0]
    record_job(role, job_id=job_id)
    return job_id


def record_job(role: str, **figures) -> None:
    """Append ``{"role": role, **figures}`` to the AESPLAT_SLURM_RECORD_JOBS file, when it is set."""
    if RECORD_JOBS:
        with open(RECORD_JOBS, "a") as record:
            record.write(json.dumps({"role": role, **figures}) + "\n")


def job_info(env: dict, job_id: str) -> dict[str, str]:
    """``scontrol show job`` as a dict (JobState, Restarts, ExitCode, ...)."""
    proc = subprocess.run(["scontrol", "show", "job", "-o", job_id], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return dict(re.findall(r"(\w+)=(\S*)", proc.stdout))


def wait_until(condition, what: str, timeout: float = 1200.0, every: float = 0.5):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = condition()
        if result:
            return result
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def wait_for_end(env: dict, job_id: str, log: Path, timeout: float = 1200.0) -> dict[str, str]:
    def ended():
        info = job_info(env, job_id)
        return info if info["JobState"] in FINAL_STATES else None

    try:
        info = wait_until(ended, f"job {job_id} to end", timeout)
    except AssertionError:
        subprocess.run(["scancel", job_id], env=env)  # do not leave it to hold the node for the next tests
        raise
    info["log"] = log.read_text() if log.exists() else ""
    return info


def weights(path: Path) -> dict[str, torch.Tensor]:
    ckpt = torch.load(path, weights_only=True, map_location="cpu")
    return {"global_step": ckpt["global_step"], **ckpt["state_dict"]}
