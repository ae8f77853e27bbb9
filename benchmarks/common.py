"""What the benchmarks and the scripts beside them share: when, where and under what load a figure was
measured (``provenance``), the writer that puts a result file down whole (``write_whole``), and the
small-sample statistics of the experiments' tables (the mean and its 95 % Student-t interval over seeds, the
paired t-test's p-value, Holm's adjustment of a family of p-values).

A file of ``benchmarks/`` imports it by name (``from common import ...``, its folder is on ``sys.path``); a file
of ``scripts/`` puts ``benchmarks/`` on ``sys.path`` first. Nothing here imports torch at import time:
``provenance()`` records torch's version only in a process that uses it, ``versions()`` imports it when called.
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterable
from datetime import datetime, timezone
from pathlib import Path

from aesplat.files import atomic_write

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


# ---------------------------------------------------------------------------------------------------
# Statistics over seeds

# Two-sided 95 % quantiles of Student's t, by degrees of freedom (beyond 30: the normal 1.96).
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
       2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045,
       2.042)  # fmt: skip


def t_quantile_95(df: int) -> float:
    """Two-sided 95 % quantile of Student's t with ``df`` >= 1 degrees of freedom."""
    if df < 1:
        raise ValueError(f"a t-interval needs at least 2 values (df >= 1), got df={df}")
    return T95[df - 1] if df <= len(T95) else 1.96


def t_interval(values: Iterable[float | None]) -> tuple[float, float, int]:
    """(mean, half-width of the 95 % t-interval, n) of the finite values; half-width NaN below 2 values."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return math.nan, math.nan, 0
    mean = sum(finite) / n
    if n < 2:
        return mean, math.nan, n
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    return mean, t_quantile_95(n - 1) * sd / math.sqrt(n), n


def t_two_sided_p(t: float, df: int) -> float:
    """Two-sided p-value of Student's t statistic ``t`` with ``df`` >= 1 (integer) degrees of freedom.

    Exact closed form for integer df (Abramowitz & Stegun 26.7.3-4): with theta = atan(|t| / sqrt(df)),
    P(|T| <= |t|) is a finite series in sin(theta) and cos(theta)^2.
    """
    if df < 1:
        raise ValueError(f"a t-test needs df >= 1, got df={df}")
    if not math.isfinite(t):
        return 0.0 if math.isinf(t) else math.nan
    theta = math.atan(abs(t) / math.sqrt(df))
    s, c2 = math.sin(theta), math.cos(theta) ** 2
    if df % 2 == 1:  # odd: 2/pi * (theta + sin cos * [1 + 2/3 c^2 + 2*4/(3*5) c^4 + ... up to c^(df-3)])
        term, series = 1.0, 1.0 if df > 1 else 0.0
        for k in range(1, (df - 1) // 2):
            term *= c2 * (2 * k) / (2 * k + 1)
            series += term
        inside = 2.0 / math.pi * (theta + s * math.cos(theta) * series)
    else:  # even: sin * [1 + 1/2 c^2 + 1*3/(2*4) c^4 + ... up to c^(df-2)]
        term, series = 1.0, 1.0
        for k in range(1, df // 2):
            term *= c2 * (2 * k - 1) / (2 * k)
            series += term
        inside = s * series
    return min(1.0, max(0.0, 1.0 - inside))


def paired_t_p(differences: Iterable[float | None]) -> tuple[float, int]:
    """(two-sided p-value of the paired t-test that the mean difference is 0, n) over the finite values; NaN
    below 2 values, 0 when every difference is the same non-zero value."""
    finite = [v for v in differences if v is not None and math.isfinite(v)]
    n = len(finite)
    if n < 2:
        return math.nan, n
    mean = sum(finite) / n
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    if sd == 0.0:
        return (1.0 if mean == 0.0 else 0.0), n
    return t_two_sided_p(mean / (sd / math.sqrt(n)), n - 1), n


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of a family of p-values (same order as given; NaN stays NaN and does not
    count towards the family's size). Rejecting where the adjusted value is <= alpha keeps the family-wise
    error rate at alpha."""
    order = sorted((i for i, p in enumerate(p_values) if math.isfinite(p)), key=lambda i: p_values[i])
    m, out, running = len(order), [math.nan] * len(p_values), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        out[i] = running
    return out
