#!/usr/bin/env python
"""Wall times of the SLURM jobs the `slurm` tests submit (tests/train/test_slurm_jobs.py), from slurmctld's log.

    python scripts/slurm_jobs.py [--runs 2] [--out docs/results/slurm]

Each run is one ``pytest -m slurm tests/train/test_slurm_jobs.py`` (the tests, unchanged, submitting the
shipped slurm/train.sbatch and slurm/eval.sbatch to the local cluster's two nodes) with
AESPLAT_SLURM_RECORD_JOBS set, so the tests write down which job id was which job. The times come from
slurmctld's own log (millisecond timestamps): per job, from submission to the end; for the preempted jobs (one
node with two tasks, two nodes with one each) also their phases (submission to start, start to the signal,
signal to ``Requeuing``, requeued to started again, which ``cred_expire`` holds back, and the restarted job);
for the jobs that lose a node, the seconds from the loss to the job's end, as the test measured them; the
tests' total is the one pytest prints (collection included). A cluster that answers (SLURM_CONF, else
``$AESPLAT_SLURM_DIR/slurm.conf``) is used and left running; otherwise ``slurm/local_cluster.sh start`` starts
one (as root it installs the packages when missing) and it is stopped at the end, as ``make test-slurm`` does.

Writes, whole or not at all, after every run (a run that fails is not recorded, and the command exits 1):

    --out/jobs.json    every run's figures, with the date, commit, machine and load averages of each
    --out/jobs.md      the table the SLURM results page includes (one column per run)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from pathlib import Path

import torch  # noqa: F401  (provenance() records the version of torch the tests ran with)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import provenance, write_whole  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TESTS = "tests/train/test_slurm_jobs.py"
CLUSTER = REPO / "slurm" / "local_cluster.sh"
ROLES = ("uninterrupted", "preempted", "two-nodes", "two-nodes-preempted", "lost-node-killed",
         "lost-node-frozen", "eval", "mismatch")  # fmt: skip
# slurmctld's log lines for the moments of a batch job (SLURM 22.05 wording); a job may start twice
# (requeued), by the main scheduler ("sched: Allocate") or the backfill one ("_start_job: Started").
EVENTS = {
    "submit": re.compile(r"_slurm_rpc_submit_batch_job: JobId=(\d+)\b"),
    "start": re.compile(r"(?:sched: Allocate|_start_job: Started) JobId=(\d+)\b"),
    "signal": re.compile(r"REQUEST_KILL_JOB JobId=(\d+)\b"),  # `scancel --signal=USR1`
    "requeue": re.compile(r"Requeuing JobId=(\d+)\b"),
    # a job ends done, or killed with a node that stopped answering (NODE_FAIL)
    "end": re.compile(r"(?:_job_complete: JobId=(\d+) done|Killing JobId=(\d+) on failed node)"),
}
LINE = re.compile(r"^\[(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?)\] (.*)$")
SUMMARY = re.compile(r"\bpassed\b.* in ([\d.]+)s\b")  # pytest's last line: "4 passed in 64.58s (0:01:04)"


class MeasureError(Exception):
    """The measurement cannot go on: one line that says why."""


class JobEvents:
    """The times (seconds since the epoch of the log's clock) at which slurmctld logged a job's moments, in
    the log's order: ``times[name]`` for each name of ``EVENTS``."""

    def __init__(self) -> None:
        self.times: dict[str, list[float]] = {name: [] for name in EVENTS}

    def first(self, name: str, job_id: str) -> float:
        if not self.times[name]:
            raise MeasureError(f"slurmctld's log has no '{name}' line for job {job_id}")
        return self.times[name][0]

    def last(self, name: str, job_id: str) -> float:
        self.first(name, job_id)
        return self.times[name][-1]


def parse_log(text: str) -> dict[str, JobEvents]:
    """Job id -> its events, from slurmctld log lines (``[2026-11-26T09:41:01.248] message``)."""
    jobs: dict[str, JobEvents] = {}
    for line in text.splitlines():
        match = LINE.match(line)
        if not match:
            continue
        stamp, message = match.groups()
        for name, pattern in EVENTS.items():
            found = pattern.search(message)
            if found:
                when = datetime.fromisoformat(stamp).timestamp()
                job_id = next(g for g in found.groups() if g)
                jobs.setdefault(job_id, JobEvents()).times[name].append(when)
    return jobs


def job_times(role: str, job_id: str, events: JobEvents) -> dict:
    """Seconds from submission to start and to the end; for the preempted job its phases as well."""
    submit, end = events.first("submit", job_id), events.last("end", job_id)
    start = events.first("start", job_id)
    out = {"job_id": job_id, "seconds": end - submit, "queued": start - submit}
    if role.endswith("preempted"):
        starts = events.times["start"]
        requeues = len(events.times["requeue"])
        if len(starts) != 2 or requeues != 1:
            raise MeasureError(f"job {job_id} ({role}) started {len(starts)} times and was requeued "
                               f"{requeues} times in slurmctld's log; expected 2 and 1")  # fmt: skip
        signal, requeue = events.first("signal", job_id), events.first("requeue", job_id)
        out["phases"] = {
            "start_to_signal": signal - start,
            "signal_to_requeue": requeue - signal,
            "held": starts[1] - requeue,
            "restarted": end - starts[1],
        }
    return out


def test_times(junit: Path, summary: str) -> dict:
    """Every test must have passed (pytest's JUnit XML); their total is the one pytest's summary line prints
    (``4 passed in 64.58s``, collection included, what ``make test-slurm`` shows), per test and without the
    collection the XML's."""
    suite = ET.parse(junit).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    if not counts["tests"] or counts["failures"] or counts["errors"] or counts["skipped"]:
        raise MeasureError(f"the slurm tests did not all pass: {counts} (their output is above)")
    per_test = {case.get("name"): float(case.get("time")) for case in suite.iter("testcase")}
    total = SUMMARY.search(summary)
    if total is None:
        raise MeasureError(f"no 'passed in N s' in pytest's summary line {summary!r}")
    return {"seconds": float(total.group(1)), "suite_seconds": float(suite.get("time")),
            "passed": counts["tests"], "per_test": per_test}  # fmt: skip


def cluster_env() -> dict[str, str]:
    slurm_dir = Path(os.environ.get("AESPLAT_SLURM_DIR", "/tmp/aesplat-slurm"))
    return {**os.environ, "SLURM_CONF": os.environ.get("SLURM_CONF") or str(slurm_dir / "slurm.conf")}


def cluster_answers(env: dict[str, str]) -> bool:
    try:
        proc = subprocess.run(["sinfo", "-h", "-o", "%T"], env=env, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0 and bool(proc.stdout.strip())


def cluster_config(env: dict[str, str]) -> dict:
    """The settings that shape the timings, from ``scontrol show config``."""
    proc = subprocess.run(["scontrol", "show", "config"], env=env, capture_output=True, text=True, timeout=30)
    if proc.returncode != 0:
        raise MeasureError(f"scontrol show config failed: {proc.stderr.strip()[-200:]}")
    config = dict(re.findall(r"^(\w+)\s+=\s+(.*?)\s*$", proc.stdout, re.MULTILINE))
    expire = re.search(r"cred_expire=(\d+)", config.get("AuthInfo", ""))
    return {
        "slurm": config.get("SLURM_VERSION"),
        "log": config.get("SlurmctldLogFile"),
        "cred_expire_s": int(expire.group(1)) if expire else 120,  # SLURM's default
        "kill_wait": config.get("KillWait"),
    }


def measure(run: int, env: dict[str, str], log: Path) -> dict:
    """One pytest run of the tests; its figures."""
    load_start = [round(v, 2) for v in os.getloadavg()]
    offset = log.stat().st_size  # the log of a reused cluster holds earlier jobs with the same ids
    with tempfile.TemporaryDirectory(prefix="slurm_jobs.") as tmp:
        record, junit = Path(tmp) / "jobs.jsonl", Path(tmp) / "junit.xml"
        command = [sys.executable, "-m", "pytest", "-q", "-m", "slurm", "-p", "no:cacheprovider",
                   f"--junitxml={junit}", TESTS]  # fmt: skip
        print(f"run {run}: {' '.join(command[1:])}", flush=True)
        started = time.monotonic()
        summary = ""
        with subprocess.Popen(command, cwd=REPO, env={**env, "AESPLAT_SLURM_RECORD_JOBS": str(record)},
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:  # fmt: skip
            for line in proc.stdout:  # shown as it comes (pytest's progress), its summary line kept
                sys.stdout.write(line)
                sys.stdout.flush()
                summary = line.strip() or summary
        wall = time.monotonic() - started
        if not junit.exists():
            raise MeasureError(f"run {run}: pytest ended with status {proc.returncode} before any test ran")
        tests = test_times(junit, summary)
        roles, measured = {}, {}
        for line in record.read_text().splitlines():
            entry = json.loads(line)
            if "job_id" in entry:
                roles[entry["role"]] = entry["job_id"]
            measured.setdefault(entry["role"], {}).update({k: v for k, v in entry.items() if k != "job_id"})
    if sorted(roles) != sorted(ROLES):
        raise MeasureError(f"run {run}: the tests recorded the jobs {sorted(roles)}, expected {list(ROLES)}")
    deadline = time.monotonic() + 10  # slurmctld may log a job's end just after the tests saw it
    while True:
        with open(log, "rb") as f:
            f.seek(offset)
            events = parse_log(f.read().decode(errors="replace"))
        ended = {job_id for job_id, job in events.items() if job.times["end"]}
        missing = [role for role, job_id in roles.items() if job_id not in ended]
        if not missing:
            break
        if time.monotonic() > deadline:
            raise MeasureError(f"run {run}: slurmctld's log ({log}) shows no end of the jobs {missing}")
        time.sleep(0.5)
    jobs = {role: job_times(role, roles[role], events[roles[role]]) for role in ROLES}
    for role in ("lost-node-killed", "lost-node-frozen"):
        if "after_loss" not in measured.get(role, {}):
            raise MeasureError(f"run {run}: the test recorded no seconds from the loss to the end of {role}")
        jobs[role]["after_loss"] = measured[role]["after_loss"]
    load_end = [round(v, 2) for v in os.getloadavg()]
    return {"run": run, "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "load": {"start": load_start, "end": load_end}, "pytest_wall_seconds": wall, "tests": tests,
            "jobs": jobs}  # fmt: skip


PREEMPTED = ("jobs", "preempted")
ROWS = [  # label, path into a run's figures
    ("2-task CPU training, 6 steps (uninterrupted)", ("jobs", "uninterrupted", "seconds")),
    ("the same job preempted during step 3, requeued, resumed", (*PREEMPTED, "seconds")),
    ("— submission to start", (*PREEMPTED, "queued")),
    ("— start to the signal (start-up, steps 1–2, hold)", (*PREEMPTED, "phases", "start_to_signal")),
    ("— signal to `Requeuing` (step 3, `hpc_ckpt_1.ckpt`)", (*PREEMPTED, "phases", "signal_to_requeue")),
    ("— requeued, held before it starts again (`cred_expire`)", (*PREEMPTED, "phases", "held")),
    ("— restarted job (start-up, resume, steps 4–6)", (*PREEMPTED, "phases", "restarted")),
    ("the uninterrupted job on two nodes, a task each", ("jobs", "two-nodes", "seconds")),
    ("the two-node job preempted, requeued, resumed", ("jobs", "two-nodes-preempted", "seconds")),
    ("node 2 killed before step 4: loss to the job's end", ("jobs", "lost-node-killed", "after_loss")),
    ("node 2 frozen (timeout 30 s): loss to the job's end", ("jobs", "lost-node-frozen", "after_loss")),
    ("`eval.sbatch` on the result (1 task)", ("jobs", "eval", "seconds")),
    ("tasks/GPUs mismatch (fails before `srun`)", ("jobs", "mismatch", "seconds")),
    ("the tests together (pytest, collection included)", ("tests", "seconds")),
]


def _at(data: dict, path: tuple[str, ...]) -> float:
    for key in path:
        data = data[key]
    return data


def _load(values: list[float] | None) -> str:
    return f"{values[0]:.1f}" if values else "?"


def table(record: dict) -> str:
    """The markdown the results page includes: what was measured where, and one column per run."""
    runs, machine, cluster = record["runs"], record["machine"], record["cluster"]
    header = ["job"] + [
        f"run {r['run']} (load {_load(r['load']['start'])} → {_load(r['load']['end'])})" for r in runs
    ]
    modified = " (with uncommitted changes)" if record["modified"] else ""
    about = [
        f"Measured {record['date'][:10]} at commit `{record['commit']}`{modified} on {machine['cpu']}",
        f"({machine['cores']} cores, {machine['memory_gib']} GiB), SLURM {cluster['slurm']}",
        f"(`cred_expire={cluster['cred_expire_s']}`, `KillWait={cluster['kill_wait']}`);",
        "load averages (1 minute) at the start and the end of each run. Seconds from the submission to the end",
        "of each job, from slurmctld's log (the rows marked — split the preempted job), except the rows of a",
        "lost node: from the loss to the job's end, as the test measured it; the tests' total is pytest's.",
        "Command:",
        f"`{record['command']}`.",
    ]
    lines = [
        " ".join(about),
        "",
        "| " + " | ".join(header) + " |",
        "| " + " | ".join(["---"] + ["---:"] * len(runs)) + " |",
    ]
    for label, path in ROWS:
        lines.append("| " + " | ".join([label] + [f"{_at(r, path):.1f} s" for r in runs]) + " |")
    return "\n".join(lines) + "\n"


def write(out: Path, record: dict) -> None:
    write_whole(out / "jobs.json", (json.dumps(record, indent=1) + "\n").encode())
    write_whole(out / "jobs.md", table(record).encode())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=2, help="how many times to run the tests (default 2)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "slurm",
                        help="folder for jobs.json and jobs.md (default docs/results/slurm)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.runs < 1:
        raise SystemExit("slurm_jobs: --runs must be at least 1")
    env = cluster_env()
    started_here = False
    try:
        if not cluster_answers(env):
            print("slurm_jobs: no cluster answers; starting slurm/local_cluster.sh", flush=True)
            if subprocess.run([str(CLUSTER), "start"], env=env).returncode != 0:
                raise MeasureError("slurm/local_cluster.sh start failed (its message is above)")
            started_here = True
        cluster = cluster_config(env)
        if not cluster["log"] or not os.access(cluster["log"], os.R_OK):
            raise MeasureError(f"cannot read slurmctld's log {cluster['log']!r} (run as its SlurmUser)")
        load_start = [round(v, 2) for v in os.getloadavg()]
        given = sys.argv[1:] if argv is None else argv
        command = shlex.join(["python", "scripts/slurm_jobs.py", *given])
        runs = []
        for run in range(1, args.runs + 1):
            runs.append(measure(run, env, Path(cluster["log"])))
            record = {"command": command, **provenance(load_start), "cluster": cluster, "runs": runs}
            write(args.out, record)
            print(f"run {run}: written to {args.out}/jobs.json and jobs.md", flush=True)
    except MeasureError as error:
        print(f"slurm_jobs: {error}", file=sys.stderr)
        return 1
    finally:
        if started_here:
            subprocess.run([str(CLUSTER), "stop"], env=env)
    print(table(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
