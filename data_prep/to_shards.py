#!/usr/bin/env python
"""Convert pixelSplat-style chunks (RealEstate10K, ACID, the synthetic set) or posed captures (DL3DV,
ScanNet++, your own COLMAP run) into WebDataset shards.

    python data_prep/to_shards.py --src DIR --out OUT [--size 256 --eval-index FILE --workers N]
    python data_prep/to_shards.py --format nerfstudio|colmap --src DIR --out OUT [--size 256 --split test]
    python data_prep/to_shards.py --src DIR --out OUT --val-scenes 200   # RealEstate10K, ACID: no validation/

SRC holds train/ and test/ folders of *.torch chunks (each with index.json), and a validation/ folder where the
data set has one (the synthetic set). Writes OUT/{train,validation,test}/*.tar and OUT/manifest.json (counts,
skipped scenes with reasons, SHA-256 per shard). A source without validation/ gets one with --val-scenes N: N
training scenes, chosen deterministically from their keys and --seed, become the validation split (the manifest
lists them) and leave the training shards. Training validates, and selects its "best" checkpoint, on the
validation split, so no choice sees a test scene (docs/validation.md). Rerunning the same command resumes:
completed shards whose checksum matches are kept.

With --format nerfstudio or colmap, SRC holds one folder per scene (a transforms.json or a COLMAP sparse model
with its images); every scene goes to --split (test by default) as one shard, and scenes that cannot be
converted are refused with a one-line reason (docs/captures.md).

    python data_prep/to_shards.py --verify --out OUT     # check every shard against the manifest's SHA-256
"""

from __future__ import annotations

import argparse
import json
import sys

from aesplat.data.capture_shards import convert_captures
from aesplat.data.shards import convert_dataset, verify_shards
from aesplat.errors import UserError
from aesplat.threads import apply_thread_policy


def main(argv: list[str] | None = None) -> None:
    try:
        convert(argv)
    except UserError as err:  # a missing source or manifest: one line, no traceback
        sys.exit(f"to_shards.py: {err}")


def convert(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--src", help="chunk folder with train/ and test/ (pixelSplat layout), or capture folder")
    p.add_argument(
        "--format",
        choices=("chunks", "nerfstudio", "colmap"),
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
        "--context-gap", type=int, default=25, help="captures without --eval-index: context gap in frames (25)"
    )
    p.add_argument(
        "--num-targets", type=int, default=3, help="captures without --eval-index: targets between (default 3)"
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
    if a.format != "chunks":
        if a.val_scenes:
            p.error("--val-scenes holds out training scenes of a chunk source; captures go whole to --split")
        convert_capture_folders(a)
        return
    try:
        manifest = convert_chunks(a)
    except ValueError as e:  # a choice of flags that does not fit the source: one line, not a traceback
        sys.exit(f"to_shards.py: {e}")
    summary = {s: {k: v for k, v in e.items() if k != "shards"} for s, e in manifest["splits"].items()}
    print(json.dumps(summary, indent=1))


def convert_capture_folders(a: argparse.Namespace) -> None:
    """``--format nerfstudio|colmap``: one folder per scene -> shards; prints the summary and each refusal."""
    try:
        manifest = convert_captures(
            a.src, a.out, a.format, size=a.size, split=a.split, eval_index=a.eval_index, workers=a.workers,
            capture_path=a.capture_path, images=a.images, frame_order=a.frame_order, context_gap=a.context_gap,
            num_targets=a.num_targets, samples_per_scene=a.samples_per_scene, train_targets=a.train_targets,
            max_fov_deg=a.max_fov, min_baseline=a.min_baseline,
            expect_shape=a.expect_shape, jpeg_quality=a.jpeg_quality, seed=a.seed, dataset=a.dataset,
            **{k: v for k, v in (("min_gap", a.min_gap), ("max_gap", a.max_gap)) if v is not None},
        )  # fmt: skip
    except (ValueError, FileNotFoundError) as e:  # bad options or source: one line, no traceback
        sys.exit(f"error: {e}")
    for entry in manifest["splits"].values():
        for message in entry["refused"].values():
            print(f"refused: {message}", file=sys.stderr)
    summary = {
        s: {k: v for k, v in e.items() if k not in ("shards", "refused")} for s, e in manifest["splits"].items()
    }
    print(json.dumps(summary, indent=1))


def convert_chunks(a: argparse.Namespace) -> dict:
    return convert_dataset(
        a.src, a.out, size=a.size, eval_index=a.eval_index, workers=a.workers, min_gap=a.min_gap,
        max_gap=a.max_gap, samples_per_scene=a.samples_per_scene, train_targets=a.train_targets,
        max_fov_deg=a.max_fov, min_baseline=a.min_baseline, expect_shape=a.expect_shape,
        jpeg_quality=a.jpeg_quality, seed=a.seed, dataset=a.dataset, specular_threshold=a.specular_threshold,
        val_scenes=a.val_scenes, val_index=a.val_index,
    )  # fmt: skip


if __name__ == "__main__":
    main()
