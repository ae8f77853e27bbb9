"""scripts/slurm_jobs.py: the job times it reads from slurmctld's log, pytest's times, and its table."""

import json

import pytest

from tests.script_loader import load_script

# slurmctld 22.05 log lines of the four jobs of one run (job 2 preempted and requeued), with unrelated lines.
LOG = """\
[2026-11-26T09:36:44.990] Running as primary controller
[2026-11-26T09:41:01.248] _slurm_rpc_submit_batch_job: JobId=1 InitPrio=4294901759 usec=568
[2026-11-26T09:41:02.035] sched/backfill: _start_job: Started JobId=1 in local on vm
[2026-11-26T09:41:10.174] _job_complete: JobId=1 WEXITSTATUS 0
[2026-11-26T09:41:10.174] _job_complete: JobId=1 done
[2026-11-26T09:41:10.541] _slurm_rpc_submit_batch_job: JobId=2 InitPrio=4294901758 usec=228
[2026-11-26T09:41:10.709] sched: Allocate JobId=2 NodeList=vm #CPUs=2 Partition=local
[2026-11-26T09:41:16.666] _slurm_rpc_kill_job: REQUEST_KILL_JOB JobId=2 uid 0
[2026-11-26T09:41:18.575] Requeuing JobId=2
[2026-11-26T09:41:50.782] sched: Allocate JobId=2 NodeList=vm #CPUs=2 Partition=local
[2026-11-26T09:41:59.252] _job_complete: JobId=2 WEXITSTATUS 0
[2026-11-26T09:41:59.252] _job_complete: JobId=2 done
[2026-11-26T09:42:00.095] _slurm_rpc_submit_batch_job: JobId=3 InitPrio=4294901757 usec=260
[2026-11-26T09:42:00.803] sched: Allocate JobId=3 NodeList=vm #CPUs=1 Partition=local
[2026-11-26T09:42:06.645] _job_complete: JobId=3 done
[2026-11-26T09:42:06.683] _slurm_rpc_submit_batch_job: JobId=4 InitPrio=4294901756 usec=346
[2026-11-26T09:42:06.815] sched: Allocate JobId=4 NodeList=vm #CPUs=1 Partition=local
[2026-11-26T09:42:06.835] _job_complete: JobId=4 WEXITSTATUS 2
[2026-11-26T09:42:06.835] _job_complete: JobId=4 done
"""
ROLES = {"uninterrupted": "1", "preempted": "2", "eval": "3", "mismatch": "4"}


@pytest.fixture(scope="module")
def bench():
    return load_script("slurm_jobs")


def test_job_times_come_from_the_log(bench):
    events = bench.parse_log(LOG)
    assert sorted(events) == ["1", "2", "3", "4"]
    jobs = {role: bench.job_times(role, job_id, events[job_id]) for role, job_id in ROLES.items()}
    assert jobs["uninterrupted"]["seconds"] == pytest.approx(10.174 - 1.248)
    assert jobs["uninterrupted"]["queued"] == pytest.approx(2.035 - 1.248)  # started by the backfill scheduler
    assert jobs["mismatch"]["seconds"] == pytest.approx(0.152)
    assert "phases" not in jobs["eval"]
    preempted = jobs["preempted"]
    assert preempted["seconds"] == pytest.approx(59.252 - 10.541)
    phases = {"start_to_signal": 16.666 - 10.709, "signal_to_requeue": 18.575 - 16.666,
              "held": 50.782 - 18.575, "restarted": 59.252 - 50.782}  # fmt: skip
    assert preempted["phases"] == pytest.approx(phases)
    # the phases and the wait in the queue add up to the whole job
    assert preempted["queued"] + sum(preempted["phases"].values()) == pytest.approx(preempted["seconds"])


def test_a_job_killed_with_a_failed_node_ends_there(bench):
    log = LOG + (
        "[2026-11-26T09:43:00.000] _slurm_rpc_submit_batch_job: JobId=5 InitPrio=4294901755 usec=300\n"
        "[2026-11-26T09:43:00.500] sched: Allocate JobId=5 NodeList=vm-[1-2] #CPUs=2 Partition=local\n"
        "[2026-11-26T09:43:51.250] Killing JobId=5 on failed node vm-2\n"
        "[2026-11-26T09:43:51.250] error: Nodes vm-2 not responding, setting DOWN\n"
    )
    times = bench.job_times("lost-node-killed", "5", bench.parse_log(log)["5"])
    assert times["seconds"] == pytest.approx(51.25)


def test_a_job_whose_moments_the_log_lacks_is_an_error(bench):
    events = bench.parse_log("\n".join(line for line in LOG.splitlines() if "Requeuing" not in line))
    with pytest.raises(bench.MeasureError, match="requeued 0 times"):
        bench.job_times("preempted", "2", events["2"])
    events = bench.parse_log("\n".join(line for line in LOG.splitlines() if "JobId=3 done" not in line))
    with pytest.raises(bench.MeasureError, match="no 'end' line for job 3"):
        bench.job_times("eval", "3", events["3"])


def _junit(tmp_path, failures=0, skipped=0):
    cases = "".join(f'<testcase classname="t" name="test_{i}" time="{10.0 * (i + 1)}"/>' for i in range(4))
    path = tmp_path / "junit.xml"
    suite = f'name="pytest" errors="0" failures="{failures}" skipped="{skipped}" tests="4" time="101.5"'
    path.write_text(f"<testsuites><testsuite {suite}>{cases}</testsuite></testsuites>")
    return path


def test_pytest_times_and_a_run_that_did_not_pass(bench, tmp_path):
    summary = "==== 4 passed in 102.34s (0:01:42) ===="
    times = bench.test_times(_junit(tmp_path), summary)
    assert (times["seconds"], times["suite_seconds"], times["passed"]) == (102.34, 101.5, 4)
    assert times["per_test"]["test_3"] == 40.0
    assert bench.test_times(_junit(tmp_path), "4 passed in 7.01s")["seconds"] == 7.01
    for counts in ({"failures": 1}, {"skipped": 4}):
        with pytest.raises(bench.MeasureError, match="did not all pass"):
            bench.test_times(_junit(tmp_path, **counts), summary)
    with pytest.raises(bench.MeasureError, match="summary line"):
        bench.test_times(_junit(tmp_path), "")


def test_the_table_has_a_column_per_run_and_says_where_it_was_measured(bench, tmp_path):
    events = bench.parse_log(LOG)
    # the two-node jobs as the log's one-node ones (same moments), the lost-node jobs with the test's seconds
    same = {**ROLES, "two-nodes": "1", "two-nodes-preempted": "2", "lost-node-killed": "3",
            "lost-node-frozen": "4"}  # fmt: skip
    runs = [
        {"run": r, "load": {"start": [1.5 * r, 1, 1], "end": [2.0, 1, 1]}, "tests": {"seconds": 70.0 + r},
         "jobs": {role: bench.job_times(role, job_id, events[job_id]) for role, job_id in same.items()}}
        for r in (1, 2)
    ]  # fmt: skip
    for r, run in enumerate(runs):
        run["jobs"]["lost-node-killed"]["after_loss"] = 12.25 + r
        run["jobs"]["lost-node-frozen"]["after_loss"] = 41.0
    record = {"command": "python scripts/slurm_jobs.py", "date": "2026-11-26T10:00:00+00:00",
              "commit": "abc1234", "modified": False, "runs": runs,
              "machine": {"cpu": "CPU X", "cores": 2, "memory_gib": 24},
              "cluster": {"slurm": "22.05.8", "cred_expire_s": 30, "kill_wait": "10 sec"}}  # fmt: skip
    bench.write(tmp_path, record)
    assert json.loads((tmp_path / "jobs.json").read_text()) == record
    text = (tmp_path / "jobs.md").read_text()
    assert "2026-11-26 at commit `abc1234` on CPU X (2 cores, 24 GiB), SLURM 22.05.8" in text
    rows = [line for line in text.splitlines() if line.startswith("|")]
    assert rows[0] == "| job | run 1 (load 1.5 → 2.0) | run 2 (load 3.0 → 2.0) |"
    assert len(rows) == 2 + len(bench.ROWS)
    assert "| 2-task CPU training, 6 steps (uninterrupted) | 8.9 s | 8.9 s |" in rows
    assert rows[-1] == "| the tests together (pytest, collection included) | 71.0 s | 72.0 s |"
    assert "| node 2 killed before step 4: loss to the job's end | 12.2 s | 13.2 s |" in rows
    assert "| the two-node job preempted, requeued, resumed | 48.7 s | 48.7 s |" in rows
    held = next(row for row in rows if "cred_expire" in row)
    assert held.endswith("| 32.2 s | 32.2 s |")
