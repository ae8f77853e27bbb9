"""benchmarks/gpu_offline.sh: wheels installed without an index, parts under their own limits, and everything
finished so far packed into OUT after each part (rehearsed on the CPU with the smoke config)."""

import json
import os
import subprocess
import sys
import tarfile
import zipfile

from tests.helpers import REPO

SCRIPT = REPO / "benchmarks" / "gpu_offline.sh"


def _wheel(folder):
    """A one-module wheel, ``offline_probe``, written by hand (no build tool, no index)."""
    folder.mkdir(parents=True)
    info = "offline_probe-1.0.dist-info"
    files = {
        "offline_probe.py": "VALUE = 1\n",
        f"{info}/METADATA": "Metadata-Version: 2.1\nName: offline-probe\nVersion: 1.0\n",
        f"{info}/WHEEL": "Wheel-Version: 1.0\nGenerator: hand\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = "".join(f"{name},,\n" for name in [*files, f"{info}/RECORD"])
    with zipfile.ZipFile(folder / "offline_probe-1.0-py3-none-any.whl", "w") as z:
        for name, text in {**files, f"{info}/RECORD": record}.items():
            z.writestr(name, text)
    return folder


def _offline(tmp_path, *args, **env_vars):
    places = {"SITE": str(tmp_path / "site"), "WORK": str(tmp_path / "work")}
    env = {**os.environ, "PYTHON": sys.executable, **places, **env_vars}
    return subprocess.run(["bash", str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=600)


def test_no_wheels_is_one_line_before_any_work(tmp_path):
    (tmp_path / "empty").mkdir()
    done = _offline(tmp_path, str(tmp_path / "empty"), str(tmp_path / "out"))
    assert done.returncode == 2 and done.stderr.strip() == f"gpu_offline.sh: no wheels in {tmp_path / 'empty'}"
    assert not (tmp_path / "out").exists()
    usage = _offline(tmp_path, str(tmp_path / "empty"))
    assert usage.returncode == 2 and usage.stderr.startswith("usage: bash benchmarks/gpu_offline.sh")


def test_a_part_past_its_limit_is_reported_and_the_next_one_still_packs_its_figures(tmp_path):
    wheels, out = _wheel(tmp_path / "wheels"), tmp_path / "out"
    done = _offline(tmp_path, str(wheels), str(out), "fit-3", "fit", DEVICE="cpu", CONFIG="conf/smoke.yaml",
                    FIT_STEPS="4", FIT_WINDOW="2", LIMITS="fit-3=1")  # fmt: skip
    log = (out / "progress.log").read_text()
    assert done.returncode == 124, log
    assert (tmp_path / "site" / "offline_probe.py").is_file() and "installed 1 wheels" in log
    assert "gpu_offline.sh: fit-3 stopped at its limit of 1 s" in log
    with tarfile.open(out / "reports.tgz") as tar:
        names = {n.removeprefix("./") for n in tar.getnames()}
        fit = json.load(tar.extractfile("./fit.json"))
    assert {"fit.json", "fit.md", "versions.txt", "fit/run/metrics.csv"} <= names and "fit-3.md" not in names
    assert fit["context_views"] == 2 and fit["figures"]["skipped steps"] == 0
    assert fit["versions"]["device"] == "no CUDA"
    assert "--data.num_context_views" not in fit["command"]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = open(f"/proc/{pid}/stat").read()  # a zombie has ended
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_nothing_a_part_started_outlives_it(tmp_path):
    """A fit that heeds TERM only at its next step (here: not at all) and outlives the benchmark that started
    it would hold the GPU in the next part: each part runs in a process group that is stopped whole."""
    python = tmp_path / "python"
    python.write_text(f"""#!/usr/bin/env bash
if [[ "$*" == *fit_throughput.py* ]]; then  # the fit, in the background of its benchmark, deaf to TERM
    trap '' TERM
    (trap '' TERM; exec sleep 300 >/dev/null 2>&1) &
    echo $! >>{tmp_path / "fits"}
    [[ "$*" == */fit-3\\ * ]] && wait  # fit-3 runs on; fit's benchmark ends at once, leaving its fit behind
    exit 0
fi
exec {sys.executable} "$@"
""")
    python.chmod(0o755)
    wheels, out = _wheel(tmp_path / "wheels"), tmp_path / "out"
    done = _offline(tmp_path, str(wheels), str(out), "fit", "fit-3", DEVICE="cpu", CONFIG="conf/smoke.yaml",
                    PYTHON=str(python), LIMITS="fit-3=10", GRACE="1")  # fmt: skip
    log = (out / "progress.log").read_text()
    fits = [int(pid) for pid in (tmp_path / "fits").read_text().split()]
    assert len(fits) == 2, log  # fit ended by itself (its fit left behind), fit-3 stopped at its limit
    assert "fit-3 stopped at its limit of 10 s" in log and done.returncode == 124
    assert not any(_alive(pid) for pid in fits), "a part's process outlived it"
