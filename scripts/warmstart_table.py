#!/usr/bin/env python
"""The validation figures of posed warm starts (`make warmstart` runs) side by side: a row per validation.

    python scripts/warmstart_table.py --run 0.0=outputs/warmstart-corner/run --run 0.5=outputs/warmstart/run \
        --out docs/results/nas3r/warmstart-pixel-offset.csv

Each ``--run VALUE=RUN_DIR`` names a run's ``model.net.options.pixel_offset`` and its folder (its
``metrics.csv``, written by the CSV logger ``make warmstart`` adds); the table has ``pixel_offset``, ``step``,
``val_psnr`` and ``val_ssim`` for every validation the run logged, the last of each run first. Written whole or
not at all.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import write_whole  # noqa: E402


def rows_of(value: str, run: Path) -> list[dict]:
    with open(run / "metrics.csv", newline="") as f:
        logged = [r for r in csv.DictReader(f) if r.get("val/psnr")]
    if not logged:
        raise SystemExit(f"warmstart_table.py: {run / 'metrics.csv'} has no validation rows")
    rows = [{"pixel_offset": value, "step": int(r["step"]), "val_psnr": float(r["val/psnr"]),
             "val_ssim": float(r["val/ssim"])} for r in logged]  # fmt: skip
    return sorted(rows, key=lambda r: -r["step"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, metavar="VALUE=RUN_DIR")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, fieldnames=["pixel_offset", "step", "val_psnr", "val_ssim"])
    writer.writeheader()
    for item in args.run:
        value, _, run = item.partition("=")
        writer.writerows(rows_of(value, Path(run)))
    write_whole(args.out, table.getvalue().encode())
    print(table.getvalue(), end="")


if __name__ == "__main__":
    main()
