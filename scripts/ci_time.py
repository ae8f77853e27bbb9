#!/usr/bin/env python
"""How long CI takes: `.ci/run` on a clean clone of this repository's HEAD, timed, install included.

    python scripts/ci_time.py [--out docs/results/ci] [--keep]

Clones HEAD into a temporary folder (committed files only, as CI sees them), runs ``bash .ci/run`` there with
its output in ``ci.log`` beside the clone, and writes ``OUT/ci.json``: the wall time of the whole run, the
tests and seconds pytest printed for ``make test`` and for the older-torch leg (``make test-torch-floor``),
with the date, the commit, the machine and the load (``provenance()``). A run that fails writes nothing and
exits 1 with the end of its log. ``--keep`` keeps the clone and the log (their folder is printed). Heavy: run
it under ``flock /work/heavy.lock`` where the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from common import provenance, write_whole  # noqa: E402

# pytest's last line: "840 passed, 5 skipped, 4 deselected, 221 warnings in 327.07s (0:05:27)"
SUMMARY = re.compile(r"^=*\s*(?P<counts>\d+ \w+(?:, \d+ \w+)*) in (?P<seconds>[\d.]+)s\b")
LEGS = ("make test", "make test-torch-floor")  # the order .ci/run runs them in


class CIError(Exception):
    """CI failed, or its log lacks what the report needs."""


def pytest_legs(log: str) -> dict[str, dict]:
    """Per leg of ``LEGS``, in order: the tests that passed, were skipped, and pytest's seconds. A failed test
    in either leg, or a leg without its summary line, is a :class:`CIError`."""
    found = []
    for line in log.splitlines():
        m = SUMMARY.match(line.strip())
        if m is None:
            continue
        counts = {word: int(n) for n, word in (c.split() for c in m["counts"].split(", "))}
        if counts.get("failed") or counts.get("error") or counts.get("errors") or "passed" not in counts:
            raise CIError(f"tests failed: {line.strip()}")
        found.append({"passed": counts["passed"], "skipped": counts.get("skipped", 0),
                      "seconds": float(m["seconds"])})  # fmt: skip
    if len(found) != len(LEGS):
        raise CIError(f"expected {len(LEGS)} pytest summaries ({', '.join(LEGS)}), found {len(found)}")
    return dict(zip(LEGS, found))


def run_ci(folder: Path) -> tuple[float, str, int]:
    """Clone HEAD into ``folder/clone`` and run ``.ci/run`` there: (wall seconds, its log, exit status)."""
    clone = folder / "clone"
    subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], check=True)
    log_path = folder / "ci.log"
    start = time.monotonic()
    with open(log_path, "w") as log:
        status = subprocess.run(["bash", ".ci/run"], cwd=clone, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL).returncode  # fmt: skip
    return time.monotonic() - start, log_path.read_text(errors="replace"), status


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "ci", help="report folder")
    p.add_argument("--keep", action="store_true", help="keep the clone and ci.log")
    args = p.parse_args(argv)
    load_start = [round(v, 2) for v in os.getloadavg()]
    folder = Path(tempfile.mkdtemp(prefix="aesplat-ci-"))
    log = ""
    try:
        seconds, log, status = run_ci(folder)
        if status != 0:
            raise CIError(f".ci/run exited with {status}")
        legs = pytest_legs(log)
    except CIError as err:  # the clone and the log stay for a look
        tail = "\n".join(log.splitlines()[-40:])
        print(f"{tail}\nci_time: {err}; nothing written (log: {folder / 'ci.log'})", file=sys.stderr)
        return 1
    if not args.keep:
        shutil.rmtree(folder, ignore_errors=True)
    record = {"command": "python scripts/ci_time.py", **provenance(load_start), "seconds": round(seconds, 1),
              "legs": legs}  # fmt: skip
    write_whole(args.out / "ci.json", (json.dumps(record, indent=1) + "\n").encode())
    print(f"ci_time: .ci/run took {seconds:.0f} s; wrote {args.out / 'ci.json'}"
          + (f" (clone and log kept in {folder})" if args.keep else ""))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
