#!/usr/bin/env python
"""Convert pixelSplat-style chunks (RealEstate10K, ACID, the synthetic set) into WebDataset shards.

    python data_prep/to_shards.py --src DIR --out OUT [--size 256 --eval-index FILE --workers N]
    python data_prep/to_shards.py --src DIR --out OUT --val-scenes 200   # RealEstate10K, ACID: no validation/

SRC holds train/ and test/ folders of *.torch chunks (each with index.json), and a validation/ folder where the
data set has one (the synthetic set). Writes OUT/{train,validation,test}/*.tar and OUT/manifest.json (counts,
skipped scenes with reasons, SHA-256 per shard). A source without validation/ gets one with --val-scenes N: N
training scenes, chosen deterministically from their keys and --seed, become the validation split (the manifest
lists them) and leave the training shards. Training validates, and selects its "best" checkpoint, on the
validation split, so no choice sees a test scene (docs/validation.md). Rerunning the same command resumes:
completed shards whose checksum matches are kept.

    python data_prep/to_shards.py --verify --out OUT     # check every shard against the manifest's SHA-256
"""

from __future__ import annotations

import argparse
import json
import sys

from aesplat.data.shards import convert_dataset, verify_shards
from aesplat.threads import apply_thread_policy


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--src", help="chunk folder with train/ and test/ (pixelSplat layout)")
    p.add_argument("--out", required=True, help="shard folder to write")
    p.add_argument("--size", type=int, default=256, help="square output side in pixels (default 256)")
    p.add_argument(
        "--eval-index",
        default=None,
        help="evaluation index JSON for test/ (default SRC/evaluation_index.json if present)",
    )
    p.add_argument(
        "--val-index",
        default=None,
        help="evaluation index JSON for validation/ (default SRC/validation_index.json if present)",
    )
    p.add_argument(
        "--val-scenes",
        type=int,
        default=0,
        help="hold out this many training scenes as the validation split (sources without validation/; "
        "default 0)",
    )
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.add_argument(
        "--min-gap",
        type=int,
        default=None,
        help="smallest training context gap in frames (default SRC/dataset.json, else 25)",
    )
    p.add_argument(
        "--max-gap",
        type=int,
        default=None,
        help="largest training context gap in frames (default SRC/dataset.json, else 90)",
    )
    p.add_argument("--samples-per-scene", type=int, default=8, help="training samples per scene (default 8)")
    p.add_argument(
        "--train-targets", type=int, default=3, help="targets stored per training sample (default 3)"
    )
    p.add_argument(
        "--max-fov", type=float, default=100.0, help="skip scenes with a wider FOV, degrees (default 100)"
    )
    p.add_argument(
        "--min-baseline", type=float, default=1e-3, help="skip scenes whose cameras move less than this"
    )
    p.add_argument(
        "--expect-shape",
        type=int,
        nargs=2,
        default=None,
        metavar=("H", "W"),
        help="skip scenes whose images are not H x W (RealEstate10K: 360 640)",
    )
    p.add_argument("--jpeg-quality", type=int, default=95)
    p.add_argument("--seed", type=int, default=0, help="seed of the training-sample draw (default 0)")
    p.add_argument("--dataset", default=None, help="name written into each sample's meta (default from SRC)")
    p.add_argument(
        "--specular-threshold",
        type=float,
        default=0.05,
        help="test targets of scenes with a `specular` magnitude get KEY.tgtI.spec.png, marking the pixels "
        "whose specular term exceeds this (area-resampled like the image, then thresholded; default 0.05)",
    )
    p.add_argument("--verify", action="store_true", help="only check OUT's shards against its manifest")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: aesplat.threads)")
    a = p.parse_args(argv)
    apply_thread_policy(num_workers=a.workers if a.workers > 1 else 0, override=a.threads)
    if a.verify:
        bad = verify_shards(a.out)
        print("\n".join(f"checksum mismatch or missing: {b}" for b in bad) or f"all shards in {a.out} verified")
        sys.exit(1 if bad else 0)
    if a.src is None:
        p.error("--src is required (unless --verify)")
    if a.val_scenes < 0:
        p.error(f"--val-scenes must be >= 0, got {a.val_scenes}")
    try:
        manifest = convert(a)
    except ValueError as e:  # a choice of flags that does not fit the source: one line, not a traceback
        sys.exit(f"to_shards.py: {e}")
    summary = {s: {k: v for k, v in e.items() if k != "shards"} for s, e in manifest["splits"].items()}
    print(json.dumps(summary, indent=1))


def convert(a: argparse.Namespace) -> dict:
    return convert_dataset(
        a.src, a.out, size=a.size, eval_index=a.eval_index, workers=a.workers, min_gap=a.min_gap,
        max_gap=a.max_gap, samples_per_scene=a.samples_per_scene, train_targets=a.train_targets,
        max_fov_deg=a.max_fov, min_baseline=a.min_baseline, expect_shape=a.expect_shape,
        jpeg_quality=a.jpeg_quality, seed=a.seed, dataset=a.dataset, specular_threshold=a.specular_threshold,
        val_scenes=a.val_scenes, val_index=a.val_index,
    )  # fmt: skip


if __name__ == "__main__":
    main()
