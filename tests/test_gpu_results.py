"""scripts/gpu_results.py: a GPU run's reports kept as the source of the GPU pages' figures."""

import io
import json
import subprocess
import sys
import tarfile

from tests.helpers import REPO

SCRIPT = REPO / "scripts" / "gpu_results.py"


def _reports(path, files: dict[str, str]) -> None:
    with tarfile.open(path, "w:gz") as tar:
        for name, text in files.items():
            data = text.encode()
            info = tarfile.TarInfo(f"./{name}")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))


def _fit(views: int, seconds: float) -> str:
    figures = {"seconds per step (median)": seconds, "peak memory (GiB)": 40.0 + views, "skipped steps": 0}
    return json.dumps({"command": "aesplat fit ...", "context_views": views, "figures": figures,
                       "versions": {"device": "NVIDIA H100", "torch": "2.11.0+cu130"},
                       "date": "2026-11-28T10:00:00+00:00", "commit": "abc1234"})  # fmt: skip


def _run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True)


def test_the_summary_reads_tests_fits_and_versions(tmp_path):
    into = tmp_path / "gpu"
    into.mkdir()
    (into / "stale.json").write_text("{}")  # a previous run's file does not survive
    _reports(tmp_path / "reports.tgz", {
        "tests.md": "SKIPPED [1] a\n4 passed, 1 failed, 1 skipped, 10 deselected in 35.29s\n(tests: 44 s)\n",
        "fit.json": _fit(2, 0.3), "fit-6.json": _fit(6, 0.9), "fit-3.json": _fit(3, 0.4),
        "versions.txt": "commit 33347c1; NVIDIA H100; torch 2.11.0+cu130; gsplat 1.5.3; lightning 2.6.6\n",
    })  # fmt: skip
    done = _run(tmp_path / "reports.tgz", "--into", into)
    assert done.returncode == 0, done.stderr
    summary = json.loads((into / "summary.json").read_text())
    assert summary["tests"] == {"ran": True, "passed": 4, "failed": 1, "skipped": 1, "seconds": 35.29}
    assert [f["context_views"] for f in summary["fits"]] == [2, 3, 6]
    assert summary["by_part"]["fit-6"]["seconds per step (median)"] == 0.9
    assert summary["commit"] == "abc1234" and summary["versions"]["device"] == "NVIDIA H100"
    assert not (into / "stale.json").exists() and (into / "fit-3.json").is_file()


def test_without_fits_the_versions_file_and_the_given_commit_serve(tmp_path):
    _reports(tmp_path / "reports.tgz", {
        "fit.log": "stopped\n",
        "versions.txt": "commit 33347c1; NVIDIA H200; torch 2.11.0+cu130; gsplat 1.5.3; lightning 2.6.6\n",
    })  # fmt: skip
    given = ("--commit", "c252b0e", "--date", "2026-11-27")
    done = _run(tmp_path / "reports.tgz", "--into", tmp_path / "gpu", *given)
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "gpu" / "summary.json").read_text())
    assert summary["tests"] == {"ran": False} and summary["fits"] == []
    assert summary["commit"] == "c252b0e" and summary["date"] == "2026-11-27"
    assert summary["versions"] == {"device": "NVIDIA H200", "torch": "2.11.0+cu130", "gsplat": "1.5.3",
                                   "lightning": "2.6.6"}  # fmt: skip
    missing = _run(tmp_path / "absent.tgz")
    assert (
        missing.returncode == 1
        and missing.stderr.strip() == f"gpu_results.py: no such file: {tmp_path}/absent.tgz"
    )


def _metrics(views: int, windows: list[tuple[float, float]], repeat_last: bool = False) -> str:
    """A fit's metrics.csv as the CSV logger writes it: a row per 15-step window (seconds per step, GiB)."""
    lines = ["step,train/context_views,train/sec_per_step,train/samples_per_sec,train/peak_memory_gib,"
             "train/skipped_steps"]  # fmt: skip
    for i, (seconds, memory) in enumerate(windows):
        lines.append(f"{15 * i + 14},{views}.0,{seconds},{10 / seconds},{memory},0.0")
    if repeat_last:  # a fit stopped by a signal logs its last window again at the step it stopped
        lines.append(f"{15 * len(windows)},{lines[-1].split(',', 1)[1]}")
    return "\n".join(lines) + "\n"


def test_fits_stopped_before_their_json_are_read_from_their_logs_and_the_progress_log(tmp_path):
    progress = "\n".join([
        "== tests: 54 s; 56 s since the start",
        "gpu_offline.sh: fit stopped at its limit of 170 s", "== fit: 173 s; 229 s since the start",
        "gpu_offline.sh: fit-3 stopped at its limit of 120 s", "== fit-3: 135 s; 364 s since the start",
        "gpu_offline.sh: fit-4 failed (exit 1)", "== fit-4: 80 s; 444 s since the start",
    ]) + "\n"  # fmt: skip
    (tmp_path / "progress.log").write_text(progress)
    _reports(tmp_path / "reports.tgz", {
        "tests.md": "5 passed, 1 skipped, 1020 deselected in 33.10s\n",
        "fit.log": "| seconds per step (median) | 0.346 |\n",
        "fit/run/metrics.csv": _metrics(2, [(4.5, 48.9), (0.335, 48.9), (0.346, 48.9), (0.349, 48.9)]),
        "fit-3.log": "", "fit-3/run/metrics.csv": _metrics(3, [(3.5, 60.0), (0.391, 63.0)], repeat_last=True),
        "fit-4.log": "torch.OutOfMemoryError: CUDA out of memory. Tried to allocate 552.00 MiB.\n",
        "fit-6/run/metrics.csv": _metrics(6, [(5.0, 70.0)]),  # only the compilation window: no figure
        "versions.txt": "commit 6edb228; NVIDIA H100; torch 2.11.0+cu130; gsplat 1.5.3; lightning 2.6.6\n",
    })  # fmt: skip
    into = tmp_path / "docs" / "gpu"
    done = _run(tmp_path / "reports.tgz", "--into", into, "--progress", tmp_path / "progress.log")
    assert done.returncode == 0, done.stderr
    summary = json.loads((into / "summary.json").read_text())
    assert [(f["part"], f["context_views"], f["source"]) for f in summary["fits"]] == [
        ("fit", 2, "fit/run/metrics.csv"), ("fit-3", 3, "fit-3/run/metrics.csv")]  # fmt: skip
    fit, fit3 = summary["fits"]
    assert fit["seconds per step (median)"] == 0.346 and fit["windows after the first"] == 3
    assert fit3["windows after the first"] == 1 and fit3["peak memory (GiB)"] == 63.0
    parts = summary["parts"]
    assert parts["tests"] == {"finished": True, "out_of_memory": False, "seconds": 54}
    assert parts["fit"] == {"finished": False, "out_of_memory": False, "seconds": 173, "stopped_at_limit": 170}
    assert parts["fit-4"] == {"finished": False, "out_of_memory": True, "seconds": 80, "failed_exit": 1}
    assert "progress" not in parts and (into / "progress.log").read_text() == progress
    absent = _run(tmp_path / "reports.tgz", "--progress", tmp_path / "none.log")
    assert absent.returncode == 1
    assert absent.stderr.strip() == f"gpu_results.py: no such file: {tmp_path}/none.log"
