"""Shared fixtures: a tiny synthetic shard set (two training shards, one test shard) built once per session, and
the environment of a job submitted to a local SLURM cluster."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import REPO, make_shards
from tests.train.slurm_cluster import CLUSTER_CONF

# The smoke data: 28x28 views; context gaps 2..8 frames; depth range 0.1..20 (see conf/smoke.yaml).
SHARD_SIZE = 28


@pytest.fixture(scope="session")
def smoke_shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("smoke_data")
    return make_shards(root, SHARD_SIZE, scenes=4, test_scenes=2, seed=0, scenes_per_chunk=2)


@pytest.fixture(scope="module")
def job_env() -> dict[str, str]:
    """Environment of the submitting process (sbatch hands it to the job): cluster, CPU mode, offline wandb."""
    conf = os.environ.get("SLURM_CONF") or str(CLUSTER_CONF)
    problem = None
    if shutil.which("sbatch") is None:
        problem = "SLURM's client commands are not installed"
    else:
        try:
            proc = subprocess.run(["sinfo", "-h", "-o", "%T"], env={**os.environ, "SLURM_CONF": conf},
                                  capture_output=True, text=True, timeout=30)  # fmt: skip
        except subprocess.TimeoutExpired:  # a configuration whose controller is not running
            problem = f"no SLURM cluster answers at {conf} (sinfo waited 30 s)"
        else:
            if proc.returncode != 0 or not proc.stdout.strip():
                problem = f"no SLURM cluster answers at {conf} ({proc.stderr.strip()[-200:]})"
    if problem:
        if os.environ.get("CI") == "true":
            pytest.fail(f"{problem}; CI must start one (slurm/local_cluster.sh start, see .ci/run)")
        pytest.skip(f"{problem}: start one with `slurm/local_cluster.sh start`, or run `make test-slurm`")
    return {
        **os.environ,
        "SLURM_CONF": conf,
        "AESPLAT": str(Path(sys.executable).parent / "aesplat"),
        "AESPLAT_SLURM_CPU": "1",
        "PYTHONPATH": f"{REPO / 'src'}:{REPO}",  # this checkout, and tests.train.helpers for the recorder
        "WANDB_MODE": "offline",
        # A stale rendezvous address in the submitting shell (an earlier torchrun, or Lightning's own
        # SLURMEnvironment in this process) must not reach the ranks: train.sbatch drops it.
        "MASTER_ADDR": "stale-host.invalid",
        "MASTER_PORT": "1",
    }
