"""SLURM scripts: valid bash, consistent #SBATCH resources, the launch Lightning's SLURM environment needs."""

import os
import re
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest
from lightning.fabric.plugins.environments import SLURMEnvironment

SLURM = Path(__file__).resolve().parents[2] / "slurm"
SCRIPTS = ["train.sbatch", "eval.sbatch"]


def directives(script: Path) -> dict[str, str]:
    """#SBATCH --key=value lines -> {key: value} (flags without a value map to "")."""
    found = {}
    for line in script.read_text().splitlines():
        match = re.match(r"#SBATCH\s+--([\w-]+)(?:=(\S+))?", line)
        if match:
            found[match.group(1)] = match.group(2) or ""
    return found


@pytest.mark.parametrize("name", SCRIPTS)
def test_scripts_are_valid_bash_with_one_task_per_gpu(name):
    subprocess.run(["bash", "-n", str(SLURM / name)], check=True)
    sbatch = directives(SLURM / name)
    assert sbatch["ntasks-per-node"] == sbatch["gpus-per-node"], "Lightning needs one task per GPU"
    assert "nodes" in sbatch


def test_train_script_requeues_on_sigusr1():
    sbatch = directives(SLURM / "train.sbatch")
    assert sbatch["signal"] == "SIGUSR1@90"  # Lightning's SLURMEnvironment requeues on SIGUSR1
    assert "requeue" in sbatch


def launch(tmp_path, script: str, args: list[str], **env) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run an sbatch script as SLURM would, with a fake `srun` that records its arguments and environment."""
    record = tmp_path / "srun_args"
    fake = tmp_path / "bin" / "srun"
    fake.parent.mkdir(exist_ok=True)
    fake.write_text(f'#!/usr/bin/env bash\nprintf "%s\\n" "$@" > {record}\nenv > {record}.env\n')
    fake.chmod(0o755)
    path = f"{fake.parent}:{os.environ['PATH']}"
    environment = {**os.environ, "PATH": path, "SLURM_SUBMIT_DIR": str(tmp_path), **env}
    proc = subprocess.run(["bash", str(SLURM / script), *args], env=environment, capture_output=True, text=True)
    argv = record.read_text().splitlines() if record.exists() else []
    # Keep what srun runs: the aesplat executable and its arguments (srun's own options come before it).
    start = next((i for i, a in enumerate(argv) if a.endswith("aesplat")), len(argv))
    return proc, argv[start:]


SLURM_ENV = {  # what sbatch + srun set for a 2-node x 4-GPU job (per task: PROCID/LOCALID/NODEID)
    "SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "aesplat-train", "SLURM_NNODES": "2", "SLURM_NTASKS": "8",
    "SLURM_NTASKS_PER_NODE": "4(x2)", "SLURM_GPUS_ON_NODE": "4", "SLURM_NODELIST": "gpu[01-02]",
    "SLURM_PROCID": "5", "SLURM_LOCALID": "1", "SLURM_NODEID": "1", "SLURM_CPUS_PER_TASK": "8",
}  # fmt: skip


def test_train_launch_matches_lightning_slurm_environment(tmp_path, monkeypatch):
    proc, argv = launch(
        tmp_path, "train.sbatch", ["-c", "conf/re10k.yaml", "--data.batch_size", "2"], **SLURM_ENV
    )
    assert proc.returncode == 0, proc.stderr
    assert argv[0].endswith("aesplat") and argv[1] == "fit"
    # The accelerator is a default the user's configs and overrides may change; what follows from the
    # allocation (devices, nodes) and the resume come after them.
    assert argv[2:7] == ["--trainer.accelerator=gpu", "-c", "conf/re10k.yaml", "--data.batch_size", "2"]
    options = dict(a.split("=", 1) for a in argv if a.startswith("--") and "=" in a)
    assert options["--trainer.devices"] == "4" and options["--trainer.num_nodes"] == "2"
    assert options["--ckpt_path"] == "last", "a requeued job must resume from its run directory"

    # Lightning, inside one of those tasks, detects SLURM and accepts devices / num_nodes as launched.
    for key, value in SLURM_ENV.items():
        monkeypatch.setenv(key, value)
    for key in ("MASTER_ADDR", "MASTER_PORT"):  # SLURMEnvironment writes these into os.environ: undo on exit
        monkeypatch.setenv(key, "")
        monkeypatch.delenv(key)
    monkeypatch.setenv("SLURM_NTASKS_PER_NODE", "4")  # srun sets the plain count inside a task
    assert SLURMEnvironment.detect()
    env = SLURMEnvironment()
    env.validate_settings(
        num_devices=int(options["--trainer.devices"]), num_nodes=int(options["--trainer.num_nodes"])
    )
    assert (env.world_size(), env.global_rank(), env.local_rank(), env.node_rank()) == (8, 5, 1, 1)
    assert env.main_address == "gpu01"


def test_a_network_interface_names_the_rendezvous_address_and_the_sockets(tmp_path):
    (tmp_path / "lo").mkdir()
    # a MASTER_ADDR left in the submitting shell is replaced
    interface = {"AESPLAT_NET_IFACE": "lo", "MASTER_ADDR": "gpu09"}
    proc, _ = launch(tmp_path / "lo", "train.sbatch", [], **SLURM_ENV, **interface)
    assert proc.returncode == 0, proc.stderr
    lines = (tmp_path / "lo" / "srun_args.env").read_text().splitlines()
    env = dict(line.split("=", 1) for line in lines if "=" in line)
    keys = ("MASTER_ADDR", "NCCL_SOCKET_IFNAME", "GLOO_SOCKET_IFNAME")
    assert [env[k] for k in keys] == ["127.0.0.1", "lo", "lo"]
    (tmp_path / "none").mkdir()
    proc, argv = launch(tmp_path / "none", "train.sbatch", [], **SLURM_ENV, AESPLAT_NET_IFACE="nosuch0")
    assert proc.returncode == 2 and argv == []
    assert proc.stderr.strip().startswith("error: AESPLAT_NET_IFACE=nosuch0: no IPv4 address on that interface")


def test_train_launch_defaults_to_re10k(tmp_path):
    proc, argv = launch(tmp_path, "train.sbatch", [], **SLURM_ENV)
    assert proc.returncode == 0, proc.stderr
    assert argv[3:5] == ["-c", "conf/re10k.yaml"]


def test_cpu_switch_trains_on_the_cpu_with_any_number_of_tasks(tmp_path):
    env = {**SLURM_ENV, "AESPLAT_SLURM_CPU": "1", "SLURM_NTASKS_PER_NODE": "3(x2)"}
    env.pop("SLURM_GPUS_ON_NODE")
    proc, argv = launch(tmp_path, "train.sbatch", ["-c", "conf/smoke.yaml"], **env)
    assert proc.returncode == 0, proc.stderr
    assert argv[2:5] == ["--trainer.accelerator=cpu", "-c", "conf/smoke.yaml"]
    assert "--trainer.devices=3" in argv and "--trainer.num_nodes=2" in argv

    # The user's own accelerator wins over the script's default.
    (tmp_path / "user").mkdir()
    proc, argv = launch(tmp_path / "user", "train.sbatch", ["--trainer.accelerator", "cuda"], **SLURM_ENV)
    assert argv.index("cuda") > argv.index("--trainer.accelerator=gpu")

    (tmp_path / "bad").mkdir()
    proc, argv = launch(tmp_path / "bad", "train.sbatch", [], **{**SLURM_ENV, "AESPLAT_SLURM_CPU": "yes"})
    assert proc.returncode != 0 and not argv and "AESPLAT_SLURM_CPU" in proc.stderr


def test_train_launch_refuses_tasks_not_matching_gpus(tmp_path):
    proc, argv = launch(tmp_path, "train.sbatch", [], **{**SLURM_ENV, "SLURM_GPUS_ON_NODE": "8"})
    assert proc.returncode != 0 and not argv
    assert "--ntasks-per-node" in proc.stderr


def test_eval_launch_needs_a_checkpoint(tmp_path):
    env = {**SLURM_ENV, "SLURM_NNODES": "1", "SLURM_NTASKS": "1", "SLURM_NTASKS_PER_NODE": "1"}
    proc, argv = launch(tmp_path, "eval.sbatch", ["-c", "conf/re10k.yaml"], **env)
    assert proc.returncode != 0 and "--ckpt_path" in proc.stderr
    proc, argv = launch(
        tmp_path, "eval.sbatch", shlex.split("-c conf/re10k.yaml --ckpt_path run/last.ckpt"), **env
    )
    assert proc.returncode == 0, proc.stderr
    assert argv[1] == "test" and "--ckpt_path" in argv and "--trainer.devices=1" in argv
    assert argv[2:4] == ["--trainer.accelerator=gpu", "-c"]
    proc, argv = launch(
        tmp_path, "eval.sbatch", shlex.split("--ckpt_path x.ckpt"), **env, AESPLAT_SLURM_CPU="1"
    )
    assert proc.returncode == 0 and argv[2] == "--trainer.accelerator=cpu"


def test_train_script_passes_a_sigusr1_of_the_batch_shell_on_to_srun(tmp_path):
    """`--signal=B:USR1@90` / `scancel --signal=USR1 --batch` signal the batch shell alone: srun must get it."""
    got = tmp_path / "srun_got_usr1"
    fake = tmp_path / "bin" / "srun"
    fake.parent.mkdir()
    fake.write_text(
        f"#!/usr/bin/env bash\ntrap 'touch {got}; exit 0' USR1\nfor i in $(seq 300); do sleep 0.1; done\n"
    )
    fake.chmod(0o755)
    env = {
        **os.environ,
        **SLURM_ENV,
        "PATH": f"{fake.parent}:{os.environ['PATH']}",
        "SLURM_SUBMIT_DIR": str(tmp_path),
    }
    shell = subprocess.Popen(["bash", str(SLURM / "train.sbatch")], env=env, stdout=subprocess.PIPE, text=True)
    assert "restart 0" in shell.stdout.readline()  # the script is past its checks and about to start srun
    time.sleep(1.0)
    shell.send_signal(signal.SIGUSR1)
    assert shell.wait(timeout=20) == 0 and got.exists()
