"""The thread policy: which intra-op thread count each setting of affinity, environment and workers gives."""

import pytest
import torch

from aesplat import threads
from aesplat.cli import _local_processes
from aesplat.threads import ThreadTuner, apply_thread_policy, pick_threads, tuning_candidates, usable_cores


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


# ----------------------------------------------------------------------------------------------- ThreadTuner


def drive(tuner: ThreadTuner, seconds_at, steps: int) -> list[int]:
    """Feed ``steps`` steps whose time depends on the current count (and step); the count of every step."""
    used = []
    for step in range(steps):
        used.append(tuner.current)
        tuner.observe(seconds_at(tuner.current, step))
    return used


def test_tuning_candidates_only_with_the_automatic_choice():
    assert tuning_candidates(1, env={}, affinity=2) == (1, 2)
    assert tuning_candidates(0, env={}, affinity=2) == (2,)  # nothing to choose between
    assert tuning_candidates(1, override=1, env={}, affinity=2) == (1,)
    assert tuning_candidates(1, env={"AESPLAT_THREADS": "1"}, affinity=2) == (1,)
    assert tuning_candidates(1, env={"OMP_NUM_THREADS": "1"}, affinity=2) == (1,)
    assert tuning_candidates(1, env={}, affinity=16, processes=2) == (7,)  # DDP ranks wait for each other
    assert tuning_candidates(2, env={"SLURM_CPUS_PER_TASK": "8"}, affinity=64) == (6, 8)


def test_tuner_keeps_the_faster_count_and_starts_on_the_safe_one():
    tuner = ThreadTuner((2, 1), probe=4, settle=1, period=1000)
    used = drive(tuner, lambda c, _: {1: 0.20, 2: 0.15}[c], 40)
    assert used[0] == 1 and used[-1] == 2 and tuner.rounds == 1
    assert tuner.last_round == {1: 0.20, 2: 0.15}
    assert used.count(1) == 1 + 1 + 4  # the first step, one settling step, the probe
    tuner = ThreadTuner((1, 2), probe=4, settle=1, period=1000)
    assert drive(tuner, lambda c, _: {1: 0.15, 2: 0.20}[c], 40)[-1] == 1


def test_tuner_prefers_fewer_threads_within_the_margin():
    tuner = ThreadTuner((1, 2), probe=4, settle=0, margin=0.05, period=1000)
    assert drive(tuner, lambda c, _: {1: 0.102, 2: 0.100}[c], 30)[-1] == 1
    tuner = ThreadTuner((1, 2), probe=4, settle=0, margin=0.0, period=1000)
    assert drive(tuner, lambda c, _: {1: 0.102, 2: 0.100}[c], 30)[-1] == 2


def test_tuner_measures_again_when_the_machine_gets_busy():
    # quiet: 2 threads win; from step 100 a competitor makes 2 threads 3x slower and 1 thread a bit slower
    def seconds(c, step):
        busy = step >= 100
        return {1: 0.22 if busy else 0.20, 2: 0.45 if busy else 0.15}[c]

    tuner = ThreadTuner((1, 2), probe=4, settle=1, period=10_000, slowdown=1.5)
    used = drive(tuner, seconds, 160)
    assert used[99] == 2
    assert set(used[125:]) == {1}  # switched within a probe's worth of steps, not after `period`
    assert tuner.rounds == 2


def test_tuner_probes_again_after_a_period_and_returns_when_it_is_quiet_again():
    def seconds(c, step):
        busy = step < 100
        return {1: 0.22 if busy else 0.20, 2: 0.45 if busy else 0.15}[c]

    tuner = ThreadTuner((1, 2), probe=4, settle=1, period=50)
    used = drive(tuner, seconds, 300)
    assert used[60] == 1 and used[-1] == 2
    assert used[-40:].count(1) <= 1 + 4  # at most one re-probe of the slower count in the last 40 steps


def test_tuner_with_one_candidate_never_switches():
    tuner = ThreadTuner((3,))
    assert not tuner.active
    assert all(tuner.observe(0.1) is None for _ in range(50))
    assert tuner.steps_at == {3: 50}
    with pytest.raises(ValueError):
        ThreadTuner(())
    with pytest.raises(ValueError):
        ThreadTuner((1, 2), slowdown=1.0)


def test_tuner_at_the_fewest_threads_takes_a_slowdown_as_the_new_yardstick():
    # 1 thread wins from the start; the machine then gets busier and busier: more threads never get probed
    # for that (only by the periodic round), and the yardstick follows the load.
    def seconds(c, step):
        load = 1.0 + step / 20  # ever busier
        return {1: 0.2 * load, 2: 0.6 * load}[c]

    tuner = ThreadTuner((1, 2), probe=4, settle=1, period=10_000)
    used = drive(tuner, seconds, 400)
    assert tuner.rounds == 1 and used[-1] == 1
    assert used.count(2) == 1 + 4  # the first round's settling step and probe only


def test_tuner_waits_longer_while_rounds_confirm_the_same_winner():
    tuner = ThreadTuner((1, 2), probe=4, settle=1, period=50)
    used = drive(tuner, lambda c, _: {1: 0.2, 2: 0.3}[c], 2000)
    # without the back-off a round every ~55 steps (36 rounds); with it: 50, 100, 200, 400, 400, ... steps
    assert 5 <= tuner.rounds <= 8
    assert used.count(2) <= (tuner.rounds + 1) * 5  # 5 steps a round (one may be under way at the end)
