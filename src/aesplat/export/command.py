"""`aesplat export`: the exports of a prediction folder, after the fact.

    aesplat export PREDICT_DIR [--formats colmap,nerfstudio,splat] [--overwrite]

writes, beside what ``aesplat predict`` wrote there, ``colmap/`` (COLMAP text model and images),
``nerfstudio/`` (``transforms.json``, images, point cloud) and ``gaussians.splat``; each whole or not at all.
``aesplat predict --export FORMATS`` writes the same files in the same run.
"""

from __future__ import annotations

import argparse

from ..errors import run_reporting_user_errors
from .formats import EXPORTS, export_prediction, parse_formats


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="aesplat export",
        description="Export the cameras and Gaussians of an `aesplat predict` folder for other tools: "
        + "; ".join(f"{name} ({fmt.dest}: {fmt.description})" for name, fmt in EXPORTS.items()),
    )
    parser.add_argument("folder", metavar="PREDICT_DIR", help="the --out folder of `aesplat predict`")
    parser.add_argument("--formats", default=",".join(EXPORTS),
                        help=f"comma-separated, from {', '.join(EXPORTS)} (default: all)")  # fmt: skip
    parser.add_argument("--overwrite", action="store_true", help="replace exports that already exist")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat export`` (see ``--help``)."""
    args = build_parser().parse_args(argv)

    def run() -> int:
        written = export_prediction(args.folder, parse_formats(args.formats), overwrite=args.overwrite)
        print("aesplat export: wrote " + ", ".join(str(p) for p in written))
        return 0

    return run_reporting_user_errors("export", run)
