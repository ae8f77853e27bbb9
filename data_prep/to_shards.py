#!/usr/bin/env python
"""Convert pixelSplat-style chunks (RealEstate10K, ACID, the synthetic set) or posed captures (DL3DV,
ScanNet++, your own COLMAP run) into WebDataset shards: one pipeline, a reader per format.

    python data_prep/to_shards.py --src DIR --out OUT [--size 256 --eval-index FILE --workers N]
    python data_prep/to_shards.py --src DIR --out OUT --val-scenes 500   # RealEstate10K, ACID: no validation/
    python data_prep/to_shards.py --format nerfstudio|colmap --src DIR --out OUT [--size 256 --split test]

SRC holds train/ and test/ folders of *.torch chunks (each with index.json), and a validation/ folder where the
data set has one (the synthetic set); with --format nerfstudio or colmap, one folder per scene (a
transforms.json or a COLMAP sparse model with its images), every scene going to --split (test by default).
Writes OUT/{train,validation,test}/*.tar and OUT/manifest.json (counts, skipped scenes with reasons, SHA-256 per
shard). Training shards hold whole scenes (every frame cropped and resized once); training draws its views from
them at run time. Validation and test shards hold one deterministic sample per scene, from the evaluation index
(or a centred context pair --context-gap frames apart), with the contexts of 2 .. --eval-context-views views.
A source without validation/ gets one with --val-scenes N: N training scenes, chosen deterministically from
their keys and --seed, become the validation split (the manifest lists them) and leave the training shards.
Training validates, and selects its "best" checkpoint, on the validation split, so no choice sees a test scene
(docs/validation.md). Rerunning the same command resumes: a shard is kept when its options, its checksum and
its source files are unchanged. Scenes that cannot be converted are skipped with a one-line reason.

    python data_prep/to_shards.py --verify --out OUT     # check every shard against the manifest's SHA-256
"""

from __future__ import annotations

import argparse
import json
import sys

from aesplat.data.convert import convert_dataset
from aesplat.data.manifest import verify_shards
from aesplat.data.sources import READERS
from aesplat.errors import UserError
from aesplat.threads import apply_thread_policy

# Options of the conversion before training shards held whole scenes: refused with what replaced them.
RETIRED = {
    "--samples-per-scene": "training shards hold whole scenes and training draws fresh views at run time (the "
    "data.fixed_pool option reproduces a fixed pool of examples per scene)",
    "--train-targets": "training draws data.num_target_views targets at run time",
    "--max-gap": "the context gap is drawn at run time from the curriculum (data.gap_initial, data.gap_final)",
}


def main(argv: list[str] | None = None) -> None:
    try:
        convert(argv)
    except UserError as err:  # a missing source, a bad option, a damaged manifest, a full disk: one line
        sys.exit(f"to_shards.py: {err}")


def convert(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--src", help="chunk folder with train/ and test/ (pixelSplat layout), or capture folder")
    p.add_argument(
        "--format",
        choices=sorted(READERS),
        default="chunks",
        help="source format: pixelSplat chunks (default), or one folder per scene with a nerfstudio "
        "transforms.json / a COLMAP sparse model",
    )
    p.add_argument("--split", choices=("train", "test"), default="test", help="captures: split of every scene")
    p.add_argument(
        "--capture-path",
        default=None,
        help="captures: transforms file (nerfstudio) or model folder (COLMAP) relative to each scene folder "
        "(default: the one found in it)",
    )
    p.add_argument(
        "--images",
        default=None,
        help="captures: image folder; nerfstudio: replaces the first folder of each file_path (e.g. images_4), "
        "COLMAP: relative to the scene folder (default images)",
    )
    p.add_argument(
        "--frame-order",
        choices=("name", "file"),
        default="name",
        help="nerfstudio: frames sorted by file_path (default) or in the file's order; indices refer to it",
    )
    p.add_argument(
        "--context-gap",
        type=int,
        default=None,
        help="evaluation samples without an --eval-index entry: context gap in frames (default --min-gap)",
    )
    p.add_argument(
        "--num-targets", type=int, default=3, help="evaluation samples without an index: targets between (3)"
    )
    p.add_argument(
        "--eval-context-views",
        type=int,
        default=6,
        help="evaluation samples carry the contexts of 2 .. K views (extra frames evenly between the outer "
        "two), so `aesplat test --data.num_context_views k` evaluates k views on the same targets (default 6)",
    )
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
        help="training scenes need more frames than this, the smallest context gap of the curriculum "
        "(default SRC/dataset.json, else 25)",
    )
    p.add_argument(
        "--frame-stride",
        type=int,
        default=1,
        help="training scenes keep every n-th frame (long captures; context gaps then count kept frames; "
        "default 1: every frame)",
    )
    for retired in RETIRED:
        p.add_argument(retired, help=argparse.SUPPRESS)
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
    p.add_argument("--seed", type=int, default=0, help="seed of the --val-scenes hold-out (default 0)")
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
    for retired, why in RETIRED.items():
        if getattr(a, retired[2:].replace("-", "_")) is not None:
            p.error(f"{retired} is gone: {why}; drop it")
    apply_thread_policy(num_workers=a.workers if a.workers > 1 else 0, override=a.threads)
    if a.verify:
        bad = verify_shards(a.out)
        print("\n".join(f"checksum mismatch or missing: {b}" for b in bad) or f"all shards in {a.out} verified")
        sys.exit(1 if bad else 0)
    if a.src is None:
        p.error("--src is required (unless --verify)")
    options = {"dataset": a.dataset, "size": a.size, "min_gap": a.min_gap, "frame_stride": a.frame_stride,
               "max_fov_deg": a.max_fov, "min_baseline": a.min_baseline, "expect_shape": a.expect_shape,
               "jpeg_quality": a.jpeg_quality, "seed": a.seed, "context_gap": a.context_gap,
               "num_targets": a.num_targets, "eval_context_views": a.eval_context_views,
               "specular_threshold": a.specular_threshold}  # fmt: skip
    if a.format != "chunks":
        options.update(split=a.split, capture_path=a.capture_path, images=a.images, frame_order=a.frame_order)
    manifest = convert_dataset(a.src, a.out, a.format, eval_index=a.eval_index, val_index=a.val_index,
                               val_scenes=a.val_scenes, workers=a.workers, **options)  # fmt: skip
    hidden = ("shards", "refused", "evaluation_samples")
    summary = {s: {k: v for k, v in e.items() if k not in hidden} for s, e in manifest["splits"].items()}
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
