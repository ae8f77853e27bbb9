"""Under DDP the ranks agree on the stop and requeue flags with host tensors over a CPU process group (nothing
made or read on the training device), a rank that stopped answering is named by its silent heartbeat, and one
that is alive but later than --distributed.timeout is named as slow, with where it was; a fit that fails ends
the ranks it started before it takes back its run markers.

Real gloo process groups and a real rendezvous store, in processes of this machine; the same on a SLURM
cluster with two nodes, a node killed or frozen, is tests/train/test_slurm_jobs.py.
"""

import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import time
from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import torch.distributed as dist

from aesplat.train.run_dir import LOCK_FILE, run_artifacts
from aesplat.train.signals import BEAT_SECONDS, Heartbeat, SignalsAtStepBoundary, lost_peer
from tests.helpers import REPO


def test_the_flags_are_agreed_on_host_tensors_whatever_the_device(tmp_path):
    """A one-process gloo group: the all-reduce runs. The module sits on the meta device, whose tensors cannot
    be read back: making the flags there, or reading them from there, would fail."""
    dist.init_process_group("gloo", store=dist.FileStore(str(tmp_path / "store"), 1), rank=0, world_size=1)
    signals = SignalsAtStepBoundary()
    trainer = SimpleNamespace(world_size=2, strategy=SimpleNamespace(launcher=None))
    module = SimpleNamespace(device=torch.device("meta"))
    try:
        signals.on_train_start(trainer, module)
        assert signals.nodes == [os.environ.get("SLURMD_NODENAME") or socket.gethostname()]
        assert signals._agree(trainer, module, requeue=False) == (False, 0)
        signals.stop_signal = signal.SIGTERM
        assert signals._agree(trainer, module, requeue=False) == (False, int(signal.SIGTERM))
    finally:
        signals.on_train_end(trainer, module)
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank(rank: int, world_size: int, port: int, dies: int, answers) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world_size, timeout=timedelta(seconds=20))
    heartbeat = Heartbeat(rank, world_size)
    dist.barrier()
    if rank == dies:  # a rank lost between two collectives; rank 0 keeps the store alive
        time.sleep(2 * BEAT_SECONDS)
        os._exit(9)
    try:
        dist.all_reduce(torch.ones(1))
    except RuntimeError as err:
        answers.put((rank, lost_peer(err), heartbeat.silent()))
    else:
        answers.put((rank, None, None))
    answers.close()
    answers.join_thread()  # the answer is in the pipe before this process ends
    heartbeat.stop()  # as a fit does once it has named the lost ranks: it is leaving, not lost
    if rank == 0:  # the store lives in this process: keep it until the others have asked
        others = [f"aesplat/left/{r}" for r in range(1, world_size) if r != dies]
        heartbeat.store.wait(others, timedelta(seconds=60))
    os._exit(0)


@pytest.mark.parametrize("dies", [2, 0])
def test_the_ranks_left_name_the_one_whose_heartbeat_stopped(dies):
    """Three ranks; one is killed. The others' collective fails (a lost peer, by the words of gloo's error)
    and each names the dead rank: rank 2 by its silent count, rank 0 as the store in its process is gone."""
    context = multiprocessing.get_context("fork")
    answers = context.Queue()
    port = _free_port()
    ranks = [context.Process(target=_rank, args=(r, 3, port, dies, answers)) for r in range(3)]
    for process in ranks:
        process.start()
    got = sorted(answers.get(timeout=60) for _ in range(2))
    for process in ranks:
        process.join(timeout=30)
    survivors = sorted(set(range(3)) - {dies})
    assert got == [(r, True, [dies]) for r in survivors]


def test_an_ordinary_error_is_no_lost_peer():
    assert not lost_peer(ValueError("bad value"))
    assert not lost_peer(RuntimeError("CUDA error: an illegal memory access was encountered"))
    assert lost_peer(RuntimeError("[gloo/transport/tcp/pair.cc:561] Connection closed by peer [127.0.0.1]:1"))
    assert lost_peer(dist.DistBackendError("NCCL communicator was aborted"))


def processes_of(run_dir: Path) -> list[int]:
    """The processes whose command line names ``run_dir``: the ranks of a fit training there."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if str(run_dir).encode() in cmdline.read_bytes():
                pids.append(int(cmdline.parent.name))
        except OSError:  # ended meanwhile
            continue
    return pids


def two_rank_fit(shards: Path, run_dir: Path, callback: str, **init_args) -> tuple[int, str, list[int]]:
    """`aesplat fit` with 2 CPU ranks (Lightning starts rank 1), --distributed.timeout 10 (the least) and the
    test callback ``callback`` of tests.train.helpers; (exit status, stderr, processes of it left after it)."""
    overlay = run_dir.parent / "callback.yaml"
    args = "".join(f"        {key}: {value}\n" for key, value in init_args.items())
    overlay.write_text(f"trainer:\n  callbacks:\n    - class_path: tests.train.helpers.{callback}\n"
                       f"      init_args:\n{args}")  # fmt: skip
    command = [sys.executable, "-m", "aesplat.cli", "fit", "-c", "conf/smoke.yaml", "-c", str(overlay),
               "--data.root", str(shards), "--trainer.default_root_dir", str(run_dir),
               "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.max_steps", "2",
               "--trainer.enable_progress_bar", "false", "--distributed.timeout", "10"]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    err = run_dir.parent / "stderr.txt"  # a file, not a pipe: a rank left running would hold a pipe open
    with err.open("w") as stderr:
        proc = subprocess.run(command, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=stderr, timeout=300)
    left = processes_of(run_dir)
    for pid in left:  # a rank the fit left running: end it, the test has seen it
        os.kill(pid, signal.SIGKILL)
    return proc.returncode, err.read_text(), left


def test_a_rank_too_slow_to_start_ends_with_the_fit_and_leaves_the_run_folder_free(smoke_shards, tmp_path):
    """Rank 1 takes 40 s to start; rank 0 gives up waiting for it to join after --distributed.timeout (10 s),
    in one line. Rank 1 is gone when the command ends (it would write the run's wandb id once started), so
    the folder holds no run marker and no lock: the corrected command starts there."""
    run_dir = tmp_path / "run"
    code, err, left = two_rank_fit(smoke_shards, run_dir, "SlowToStart", rank=1, seconds=40)
    assert left == [], "a rank of the failed fit outlived it"
    assert code == 1 and "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1] == (
        "aesplat fit: 1 of the 2 ranks had not joined the process group when rank 0 gave up waiting for it "
        "after 10 s (--distributed.timeout): still starting; raise --distributed.timeout above the time the "
        "slowest rank takes to start"
    )
    assert not run_dir.exists() or (run_artifacts(run_dir) == [] and not (run_dir / LOCK_FILE).exists())


@pytest.mark.slow  # about 24 s on a 2-core machine: the 10 s timeout, 3 s of heartbeats, two ranks starting
def test_a_slow_rank_is_named_alive_with_where_it_was_and_the_fix(smoke_shards, tmp_path):
    """Rank 1 waits 25 s before its first step (as a first batch from a cold cache would): its heartbeat goes
    on, so it is not lost; rank 0 gives up after --distributed.timeout (10 s) in gloo's "Timed out waiting
    10000ms", which becomes one line naming rank 1, where each rank was, and the fix."""
    run_dir = tmp_path / "run"
    code, err, left = two_rank_fit(smoke_shards, run_dir, "SlowRank", rank=1, seconds=25)
    assert left == [], "a rank of the failed fit outlived it"
    assert code == 1 and "Traceback" not in err, err[-3000:]
    node = os.environ.get("SLURMD_NODENAME") or socket.gethostname()
    assert err.strip().splitlines()[-1] == (
        f"aesplat fit: rank 1 (node {node}) of 2 was alive but slow, still loading its batch for step 1, when "
        "rank 0 gave up waiting for it after 10 s (--distributed.timeout) in the forward pass of step 1; raise "
        "--distributed.timeout above the longest one rank can lag behind the others (a first batch from a cold "
        "cache, a checkpoint save) and resume with --ckpt_path last"
    )
    assert not run_dir.exists() or run_artifacts(run_dir) == []
