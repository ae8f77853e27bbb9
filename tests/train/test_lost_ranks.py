"""Under DDP the ranks agree on the stop and requeue flags with host tensors over a CPU process group (nothing
made or read on the training device), and a rank that stopped answering is named by its silent heartbeat.

Real gloo process groups and a real rendezvous store, in processes of this machine; the same on a SLURM
cluster with two nodes, a node killed or frozen, is tests/train/test_slurm_jobs.py.
"""

import multiprocessing
import os
import signal
import socket
import time
from datetime import timedelta
from types import SimpleNamespace

import pytest
import torch
import torch.distributed as dist

from aesplat.train.signals import BEAT_SECONDS, Heartbeat, SignalsAtStepBoundary, lost_peer


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
