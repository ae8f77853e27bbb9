#!/usr/bin/env python
"""Keep what a GPU run of benchmarks/gpu_offline.sh returned as the source of the GPU pages' figures.

    python scripts/gpu_results.py OUT/reports.tgz [--progress OUT/progress.log] [--into docs/results/gpu]

Unpacks the run's reports (each part's .md or .log and .json, the versions, the fits' metrics.csv) into INTO,
replacing what was there, with the run's progress log beside when given, and writes INTO/summary.json: the GPU
and versions, the gpu tests' outcome (counts read from pytest's closing line in tests.md), per fit part (fit,
fit-N) its context views and figures in the order of their view counts (from its .json; from its run's
metrics.csv when the part was stopped before writing one, marked by ``source``), per part whether it finished,
ran out of GPU memory, or (from the progress log) was stopped at its time limit and after how many seconds,
with the GPU and versions (the fits' files, else versions.txt) and the commit and date (``--commit``,
``--date`` where the files name none or a stale one). docs/results/gpu-training-step.md quotes these files
(scripts/figures.py checks it).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from common import write_whole  # noqa: E402

OUTCOMES = ("passed", "failed", "skipped", "error", "errors")


def test_outcome(tests_md: Path) -> dict:
    """Counts of pytest's closing line (``5 passed, 1 skipped in 80.1s``), or why there are none."""
    if not tests_md.is_file():
        return {"ran": False}
    closing = [line for line in tests_md.read_text().splitlines() if re.search(r"\d+ (passed|failed)", line)]
    if not closing:
        return {"ran": False}
    counts = {word.rstrip("s") if word == "errors" else word: int(n)
              for n, word in re.findall(r"(\d+) (" + "|".join(OUTCOMES) + r")\b", closing[-1])}  # fmt: skip
    seconds = re.search(r"in ([\d.]+)s", closing[-1])
    return {"ran": True, **counts, "seconds": float(seconds.group(1)) if seconds else None}


def versions_line(path: Path) -> dict:
    """gpu_throughput.sh's versions.txt (``commit C; GPU; torch T; gsplat G; lightning L``) as a mapping."""
    if not path.is_file():
        return {}
    fields = [f.strip() for f in path.read_text().strip().split(";")]
    out = {"device": fields[1]} if len(fields) > 1 else {}
    for field in fields:
        name, _, value = field.partition(" ")
        if name in ("commit", "torch", "gsplat", "lightning"):
            out[name] = value
    return out


FIT_PART = re.compile(r"^fit(-(\d+))?$")


def part_outcomes(folder: Path, progress: str) -> dict[str, dict]:
    """Per part that left a file: whether it finished (gpu_throughput.sh renames a part's .log to .md only when
    it succeeded), whether it ran out of GPU memory, and from gpu_offline.sh's progress log its seconds and
    whether it was stopped at its time limit or failed."""
    parts = {}
    for path in sorted(folder.glob("*.log")) + sorted(folder.glob("*.md")):
        if path.name == "progress.log":
            continue
        text = path.read_text(errors="replace")
        parts[path.stem] = {"finished": path.suffix == ".md", "out_of_memory": "OutOfMemoryError" in text}
    for name, seconds in re.findall(r"^== (\S+): (\d+) s;", progress, re.M):
        parts.setdefault(name, {"finished": False, "out_of_memory": False})["seconds"] = int(seconds)
    for name, limit in re.findall(r"^gpu_offline\.sh: (\S+) stopped at its limit of (\d+) s", progress, re.M):
        parts[name]["stopped_at_limit"] = int(limit)
    for name, code in re.findall(r"^gpu_offline\.sh: (\S+) failed \(exit (\d+)\)", progress, re.M):
        parts[name]["failed_exit"] = int(code)
    return parts


def fit_figures(folder: Path, part: str) -> dict | None:
    """A fit part's figures: its .json, else (a part stopped before writing it) its run's metrics.csv when it
    holds a window after the first, summarized as fit_throughput.py does; None when neither has figures."""
    if (folder / f"{part}.json").is_file():
        record = json.loads((folder / f"{part}.json").read_text())
        return {"part": part, "context_views": record["context_views"], "source": f"{part}.json",
                **record["figures"]}  # fmt: skip
    metrics = folder / part / "run" / "metrics.csv"
    if not metrics.is_file():
        return None
    from fit_throughput import summarize as fit_summary

    try:
        figures = fit_summary(metrics)
    except SystemExit:  # fewer than two windows: nothing after compilation
        return None
    with metrics.open(newline="") as f:
        views = {int(float(v)) for r in csv.DictReader(f) if (v := r.get("train/context_views"))}
    number = FIT_PART.match(part).group(2)
    views = views.pop() if len(views) == 1 else int(number) if number else sorted(views)
    return {"part": part, "context_views": views, "source": f"{part}/run/metrics.csv", **figures}


def summarize(folder: Path, commit: str | None = None, progress: str = "") -> dict:
    names = {p.stem for p in folder.glob("fit*.*")} | {p.name for p in folder.glob("fit*") if p.is_dir()}
    fits = [f for f in (fit_figures(folder, n) for n in sorted(names) if FIT_PART.match(n)) if f is not None]
    fits.sort(key=lambda f: (f["context_views"] if isinstance(f["context_views"], int) else 99, f["part"]))
    recorded = [json.loads((folder / f["source"]).read_text()) for f in fits if f["source"].endswith(".json")]
    first = recorded[0] if recorded else {}
    line = versions_line(folder / "versions.txt")
    return {
        "versions": first.get("versions") or {k: v for k, v in line.items() if k != "commit"},
        "date": first.get("date"),
        "commit": commit or first.get("commit") or line.get("commit"),
        "tests": test_outcome(folder / "tests.md"),
        "fits": fits,
        "by_part": {f["part"]: f for f in fits},
        "parts": part_outcomes(folder, progress),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", type=Path, help="reports.tgz of a gpu_offline.sh run")
    p.add_argument("--into", type=Path, default=REPO / "docs" / "results" / "gpu")
    p.add_argument("--commit", help="the commit the tree was sent as, where its files name none or a stale one")
    p.add_argument("--date", help="the day of the run (YYYY-MM-DD), where no figure file gives its time")
    p.add_argument("--progress", type=Path, help="gpu_offline.sh's OUT/progress.log of the run, kept beside")
    args = p.parse_args()
    for path in (args.reports, args.progress):
        if path is not None and not path.is_file():
            raise SystemExit(f"gpu_results.py: no such file: {path}")
    progress = args.progress.read_text(errors="replace") if args.progress else ""
    args.into.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.into.parent) as tmp:
        staged = Path(tmp) / "gpu"
        with tarfile.open(args.reports) as tar:
            tar.extractall(staged, filter="data")
        if args.progress:
            (staged / "progress.log").write_text(progress)
        summary = summarize(staged, args.commit, progress)
        summary["date"] = summary["date"] or args.date
        write_whole(staged / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
        if args.into.exists():
            shutil.rmtree(args.into)
        staged.rename(args.into)
    print(f"wrote {args.into} ({sum(1 for _ in args.into.rglob('*'))} files)")


if __name__ == "__main__":
    main()
