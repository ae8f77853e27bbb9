#!/usr/bin/env python
"""Keep what a GPU run of benchmarks/gpu_offline.sh returned as the source of the GPU pages' figures.

    python scripts/gpu_results.py OUT/reports.tgz [--into docs/results/gpu]

Unpacks the run's reports (each part's .md and .json, the versions, the fits' metrics.csv) into INTO, replacing
what was there, and writes INTO/summary.json: the GPU and versions, the gpu tests' outcome (counts read from
pytest's closing line in tests.md), and per fit part (fit, fit-N) its context views and figures, in the order
of their view counts, with the GPU and versions (the fits' files, else versions.txt) and the commit and date
(``--commit``, ``--date`` where the files name none or a stale one). docs/results/gpu-training-step.md quotes
these files (scripts/figures.py checks it).
"""

from __future__ import annotations

import argparse
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


def summarize(folder: Path, commit: str | None = None) -> dict:
    fits = []
    for path in sorted(folder.glob("fit*.json")):
        record = json.loads(path.read_text())
        fits.append({"part": path.stem, "context_views": record["context_views"], **record["figures"]})
    fits.sort(key=lambda f: (f["context_views"] if isinstance(f["context_views"], int) else 99, f["part"]))
    first = json.loads((folder / f"{fits[0]['part']}.json").read_text()) if fits else {}
    line = versions_line(folder / "versions.txt")
    return {
        "versions": first.get("versions") or {k: v for k, v in line.items() if k != "commit"},
        "date": first.get("date"),
        "commit": commit or first.get("commit") or line.get("commit"),
        "tests": test_outcome(folder / "tests.md"),
        "fits": fits,
        "by_part": {f["part"]: f for f in fits},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", type=Path, help="reports.tgz of a gpu_offline.sh run")
    p.add_argument("--into", type=Path, default=REPO / "docs" / "results" / "gpu")
    p.add_argument("--commit", help="the commit the tree was sent as, where its files name none or a stale one")
    p.add_argument("--date", help="the day of the run (YYYY-MM-DD), where no figure file gives its time")
    args = p.parse_args()
    if not args.reports.is_file():
        raise SystemExit(f"gpu_results.py: no such file: {args.reports}")
    with tempfile.TemporaryDirectory(dir=args.into.parent) as tmp:
        staged = Path(tmp) / "gpu"
        with tarfile.open(args.reports) as tar:
            tar.extractall(staged, filter="data")
        summary = summarize(staged, args.commit)
        summary["date"] = summary["date"] or args.date
        write_whole(staged / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
        if args.into.exists():
            shutil.rmtree(args.into)
        staged.rename(args.into)
    print(f"wrote {args.into} ({sum(1 for _ in args.into.rglob('*'))} files)")


if __name__ == "__main__":
    main()
