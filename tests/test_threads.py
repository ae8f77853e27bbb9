"""The thread policy: which intra-op thread count each setting of affinity, environment and workers gives."""

import pytest
import torch

from aesplat import threads
from aesplat.lightning_cli import _local_processes
from aesplat.threads import apply_thread_policy, pick_threads, usable_cores


@pytest.mark.parametrize(
    ("affinity", "workers", "env", "expected"),
    [
        (2, 1, {}, 1),  # the demo on a 2-core machine: one core for the worker, one for the step
        (2, 0, {}, 2),
        (16, 4, {}, 12),
        (4, 8, {}, 1),  # more workers than cores: still one thread
        (64, 2, {"SLURM_CPUS_PER_TASK": "8"}, 6),  # the task's share, not the node's
        (4, 0, {"SLURM_CPUS_PER_TASK": "8"}, 4),  # the affinity mask is smaller still
        (16, 2, {"OMP_NUM_THREADS": "1"}, 1),  # torchrun's default caps it
        (16, 2, {"OMP_NUM_THREADS": "32"}, 14),  # a cap, never a raise
        (16, 2, {"OMP_NUM_THREADS": "4,2"}, 4),  # nested OpenMP levels: the first one
        (16, 2, {"SLURM_CPUS_PER_TASK": "", "OMP_NUM_THREADS": "x"}, 14),  # unusable values are ignored
        (2, 1, {"AESPLAT_THREADS": "3"}, 3),  # explicit: beats everything, may exceed the cores
        (16, 2, {"AESPLAT_THREADS": "2", "OMP_NUM_THREADS": "1"}, 2),
    ],
)
def test_picked_threads(affinity, workers, env, expected):
    choice = pick_threads(num_workers=workers, env=env, affinity=affinity)
    assert choice.threads == expected
    assert str(expected) in choice.reason


def test_override_beats_environment_and_bad_values_are_named():
    assert pick_threads(2, override=5, env={"AESPLAT_THREADS": "3"}, affinity=2).threads == 5
    with pytest.raises(ValueError, match="threads must be >= 1"):
        pick_threads(override=0, env={}, affinity=2)
    with pytest.raises(ValueError, match="AESPLAT_THREADS='many'"):
        pick_threads(env={"AESPLAT_THREADS": "many"}, affinity=2)


def test_cores_other_processes_keep_busy_are_left_to_them():
    busy = pick_threads(0, env={}, affinity=2, busy_cores=0.74)  # one spinning process beside the bench
    assert busy.threads == 1 and "1 kept busy by other processes" in busy.reason
    assert pick_threads(0, env={}, affinity=2, busy_cores=0.3).threads == 2  # less than half a core: ignored
    assert pick_threads(1, env={}, affinity=2, busy_cores=3.0).threads == 1  # at least one thread
    assert pick_threads(0, env={}, affinity=16, busy_cores=2.2).threads == 14
    assert pick_threads(0, override=2, env={}, affinity=2, busy_cores=1.0).threads == 2  # a choice stands
    assert pick_threads(0, env={"AESPLAT_THREADS": "2"}, affinity=2, busy_cores=1.0).threads == 2


def test_processes_of_one_node_share_its_cores_unless_slurm_says_per_task():
    assert usable_cores(env={}, affinity=16, processes=4) == 4
    assert usable_cores(env={}, affinity=2, processes=4) == 1
    assert usable_cores(env={"SLURM_CPUS_PER_TASK": "6"}, affinity=64, processes=4) == 6
    assert pick_threads(1, env={}, affinity=16, processes=2).threads == 7


def test_default_affinity_is_this_process_mask(monkeypatch):
    monkeypatch.setattr(threads.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    assert usable_cores(env={}) == 3
    assert pick_threads(1, env={}).threads == 2


def test_apply_sets_torch_threads_and_reports_once(monkeypatch, capsys):
    before = torch.get_num_threads()
    monkeypatch.setattr(threads, "_applied", None)
    monkeypatch.setenv("AESPLAT_THREADS", "1")
    try:
        assert apply_thread_policy(num_workers=3) == 1
        assert torch.get_num_threads() == 1
        apply_thread_policy(num_workers=3)
        assert capsys.readouterr().err.count("torch CPU threads: 1") == 1
        monkeypatch.setenv("AESPLAT_THREADS", "none")
        with pytest.raises(SystemExit, match="AESPLAT_THREADS='none'"):
            apply_thread_policy()
    finally:
        torch.set_num_threads(before)


def test_cli_counts_cpu_ddp_processes():
    assert _local_processes({"accelerator": "cpu", "devices": 2}) == 2
    assert _local_processes({"accelerator": "cpu", "devices": 1}) == 1
    assert _local_processes({"accelerator": "gpu", "devices": 4}) == 1
    assert _local_processes({"accelerator": "cpu", "devices": "auto"}) == 1
