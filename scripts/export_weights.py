#!/usr/bin/env python
"""Keep only the model of an `aesplat fit` checkpoint: a smaller file for ``model.net.weights``.

    python scripts/export_weights.py --ckpt outputs/warmstart/run/checkpoints/last.ckpt \
        --out weights/demo-warmstart.pt [--note "how it was made"]

The file holds the model's tensors (fp32), the run's hyper-parameters (so a mismatching ``model.net`` is named
in the error) and the note; no optimizer state, metrics or loop state, so it cannot resume a fit.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", type=Path, required=True, help="an `aesplat fit` checkpoint (.ckpt)")
    parser.add_argument("--out", type=Path, required=True, help="where to write the weights file")
    parser.add_argument(
        "--note", default="", help="kept in the file, e.g. the command that made the checkpoint"
    )
    args = parser.parse_args(argv)
    from aesplat.model.weights import export_weights

    out = export_weights(args.ckpt, args.out, args.note)
    before, after = args.ckpt.stat().st_size, out.stat().st_size
    print(f"export_weights: {out} ({after / 2**20:.1f} MiB; the checkpoint was {before / 2**20:.1f} MiB)")


if __name__ == "__main__":
    main()
