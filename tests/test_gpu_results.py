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
