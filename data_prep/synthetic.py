#!/usr/bin/env python
"""Generate the synthetic data set in the pixelSplat chunk format (no download).

    python data_prep/synthetic.py --out DIR [--scenes N --frames F --height H --width W --seed S]
    python data_prep/synthetic.py --out DIR --preset specular|diffuse ...   # the matched ablation sets

Writes DIR/{train,validation,test}/*.torch + index.json, DIR/evaluation_index.json (test),
DIR/validation_index.json and DIR/dataset.json. Each scene of a chunk also holds `specular` [F, H, W], the
magnitude of its specular term per pixel (zero for a diffuse scene). Train, validation and test scenes come from
disjoint seed streams: adding validation scenes changes no train or test scene (see docs/validation.md).
"""

from __future__ import annotations

import argparse
import time

from aesplat.data.synthetic_scenes import PRESETS, generate_dataset
from aesplat.threads import apply_thread_policy


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (train/, validation/, test/, index files)")
    p.add_argument("--scenes", type=int, default=24, help="training scenes (default 24)")
    p.add_argument("--test-scenes", type=int, default=None, help="test scenes (default: half of --scenes)")
    p.add_argument(
        "--val-scenes",
        type=int,
        default=None,
        help="validation scenes, for checkpoint selection and every choice of settings (default: a third of "
        "the test scenes; 0: none)",
    )
    p.add_argument("--frames", type=int, default=32, help="frames per scene (default 32, at least 5)")
    p.add_argument("--height", type=int, default=96, help="image height in pixels (default 96)")
    p.add_argument("--width", type=int, default=128, help="image width in pixels (default 128)")
    p.add_argument("--seed", type=int, default=0, help="everything is determined by this seed (default 0)")
    p.add_argument(
        "--supersample",
        type=int,
        default=1,
        help="anti-alias with S x S rays per pixel (about S^2 times slower; default 1)",
    )
    p.add_argument(
        "--texture-scale",
        type=float,
        default=1.0,
        help="multiply every texture's feature size (checker cells, wave periods) by this (default 1)",
    )
    p.add_argument(
        "--turn-scale",
        type=float,
        default=1.0,
        help="multiply how far each camera path turns (its change of yaw) by this (default 1)",
    )
    p.add_argument("--scenes-per-chunk", type=int, default=4, help="scenes per *.torch chunk (default 4)")
    p.add_argument("--specular", type=float, default=None, help="probability a scene declares `specular`")
    p.add_argument("--exposure", type=float, default=None, help="probability a scene declares `exposure`")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: aesplat.threads)")
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default=None,
        help="specular: every scene declares textures + specular and every surface is glossy; diffuse: the "
        "same scenes (same seed -> same geometry, materials, cameras) with the highlights off",
    )
    a = p.parse_args(argv)
    apply_thread_policy(override=a.threads)  # the ray caster itself runs its small kernels on one thread
    probs = {k: v for k, v in (("specular", a.specular), ("exposure", a.exposure)) if v is not None}
    start = time.perf_counter()
    info = generate_dataset(
        a.out, scenes=a.scenes, frames=a.frames, height=a.height, width=a.width, seed=a.seed,
        test_scenes=a.test_scenes, val_scenes=a.val_scenes, scenes_per_chunk=a.scenes_per_chunk,
        effect_probs=probs, supersample=a.supersample, texture_scale=a.texture_scale,
        turn_scale=a.turn_scale, preset=a.preset, progress=True,
    )  # fmt: skip
    n = info["train_scenes"] + info["validation_scenes"] + info["test_scenes"]
    print(f"wrote {n} scenes ({info['train_scenes']} train, {info['validation_scenes']} validation, "
          f"{info['test_scenes']} test) x {a.frames} frames "
          f"at {a.height}x{a.width} to {a.out} in {time.perf_counter() - start:.1f} s; "
          f"suggested context gaps (data.gap_final) {info['gap_range']}, depth range (model.net.near/far) "
          f"{info['near']}/{info['far']}")  # fmt: skip


if __name__ == "__main__":
    main()
