"""What the benchmarks and the scripts beside them share: when, where and under what load a figure was
measured (``provenance``), the writer that puts a result file down whole (``write_whole``), and, from
``aesplat.stats``, the small-sample statistics of the experiments' tables (the mean and its 95 % Student-t
interval over seeds, the paired t-test's p-value, Holm's adjustment of a family of p-values).

A file of ``benchmarks/`` imports it by name (``from common import ...``, its folder is on ``sys.path``); a file
of ``scripts/`` puts ``benchmarks/`` on ``sys.path`` first. Nothing here imports torch at import time:
``provenance()`` records torch's version only in a process that uses it, ``versions()`` imports it when called.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from collections.abc import Iterable
from datetime import datetime, timezone
from pathlib import Path

from aesplat.files import atomic_write

# The experiments' small-sample statistics are the package's; named here for the scripts that import them.
from aesplat.stats import T95, holm, paired_t_p, t_interval, t_quantile_95, t_two_sided_p  # noqa: F401

REPO = Path(__file__).resolve().parents[1]
AESPLAT = [sys.executable, "-m", "aesplat.cli"]  # the `aesplat` command of this interpreter's environment


def provenance(load_start: list[float] | None = None) -> dict:
    """When, on what and under what load a figure was measured: the UTC time, the commit (and whether tracked
    files other than the documentation differed from it; for a copy of the tree, ``AESPLAT_COMMIT`` when set),
    the machine, and the 1-, 5- and 15-minute load averages at the start (``load_start``, when the caller read
    them) and now."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        code = ("--", ".", ":(exclude)docs", ":(exclude)*.md")  # pages do not change a measurement
        commit = {"commit": git("rev-parse", "--short", "HEAD"),
                  "modified": bool(git("status", "--porcelain", "--untracked-files=no", *code))}  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        commit = {"commit": None, "modified": None}
    if os.environ.get("AESPLAT_COMMIT"):  # a copy of the tree sent elsewhere: its git, if any, may be stale
        commit = {"commit": os.environ["AESPLAT_COMMIT"], "modified": None}
    machine = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "memory_gib": None}
    for name, prefix in (("/proc/cpuinfo", "model name"), ("/proc/meminfo", "MemTotal:")):
        try:
            line = next(x for x in Path(name).read_text().splitlines() if x.startswith(prefix))
        except (OSError, StopIteration):
            continue
        if prefix == "model name":
            machine["cpu"] = line.split(":", 1)[1].strip()
        else:
            machine["memory_gib"] = round(int(line.split()[1]) / 2**20, 1)  # kB
    machine |= {"system": f"{platform.system()} {platform.machine()}", "python": sys.version.split()[0]}
    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        machine |= {"torch": torch.__version__, "torch_threads": torch.get_num_threads()}
    try:
        load_now = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load_now = None
    return {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), **commit, "machine": machine,
            "load": {"start": load_start, "end": load_now}}  # fmt: skip


def versions() -> dict[str, str]:
    """The GPU (or "no CUDA") and the versions of torch, gsplat and Lightning in this environment."""
    import importlib.metadata

    import torch

    def version(name: str) -> str:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return "not installed"

    device = torch.cuda.get_device_name() if torch.cuda.is_available() else "no CUDA"
    return {"device": device, "torch": torch.__version__, "gsplat": version("gsplat"),
            "lightning": version("lightning")}  # fmt: skip


def write_whole(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all (``aesplat.files.atomic_write``)."""
    atomic_write(path, lambda f: f.write(data))


# ---------------------------------------------------------------------------------------------------
# Data

DEMO_VAL_SCENES = 12  # validation scenes of the demo's shards, as scripts/demo.sh makes them


def demo_shards(
    src: Path,
    sizes: Iterable[tuple[int, Path]],
    scene_args: Iterable[str] = ("--val-scenes", str(DEMO_VAL_SCENES)),
    convert_args: Iterable[str] = (),
    **run_options,
) -> None:
    """Shards made as `make demo` makes them, each once: ``data_prep/synthetic.py --out SRC SCENE_ARGS`` (when
    SRC holds no dataset.json), then ``data_prep/to_shards.py`` into each folder of ``sizes`` (size, folder)
    that holds no manifest.json. ``run_options`` go to ``subprocess.run`` (an environment, quiet output)."""
    python = sys.executable
    sizes = [(size, out) for size, out in sizes if not (out / "manifest.json").is_file()]
    if sizes and not (src / "dataset.json").is_file():
        subprocess.run([python, str(REPO / "data_prep/synthetic.py"), "--out", str(src), *scene_args],
                       check=True, **run_options)  # fmt: skip
    for size, out in sizes:
        subprocess.run([python, str(REPO / "data_prep/to_shards.py"), "--src", str(src), "--out", str(out),
                        "--size", str(size), *convert_args], check=True, **run_options)  # fmt: skip


def synthetic_shards(root: Path, size: int, scenes: int) -> tuple[Path, list[int]]:
    """Synthetic scenes (32 frames, one test scene) as shards of ``size`` under ``root``, made in this process;
    returns the shard folder and the gap range the scenes hold."""
    from aesplat.data import convert_dataset, generate_dataset

    info = generate_dataset(root / "src", scenes=scenes, test_scenes=1, frames=32, seed=0, progress=False)
    convert_dataset(root / "src", root / "shards", size=size, progress=False)
    return root / "shards", list(info["gap_range"])
