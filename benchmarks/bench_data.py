"""Data benchmark: synthetic generation time per scene, conversion time, and loader throughput.

    python benchmarks/bench_data.py [--size 224] [--batch-size 10] [--workers 2] [--batches 40]
                                    [--gpu-steps-per-second 4] [--out DIR]

Builds a synthetic set (in a temporary folder unless --out), converts it to --size shards, then times the
training stream of the DataModule (2 context + 1 target views, uint8 batches, flip augmentation on) with
--workers DataLoader workers and in the main process. The curriculum case "paper initial range" keeps only the
smallest-gap sample of each scene (1 in 8), the worst acceptance the 25 -> 90 schedule sees. Prints markdown.
The loader must outrun the GPU: the needed rate is batch size x GPU steps per second.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from aesplat.data import DataModule, convert_dataset, generate_dataset


def time_generation(out: Path, scenes: int, frames: int, height: int, width: int) -> float:
    """Seconds per scene of ``generate_dataset`` (train + test scenes, writing included)."""
    start = time.perf_counter()
    info = generate_dataset(out, scenes=scenes, test_scenes=max(1, scenes // 4), frames=frames, height=height,
                            width=width, seed=0)  # fmt: skip
    return (time.perf_counter() - start) / (info["train_scenes"] + info["test_scenes"])


def loader_rate(
    root: Path, size: int, batch_size: int, workers: int, batches: int, gap: tuple[int, int]
) -> float:
    """Training samples per second of the DataModule's stream, after a warm-up."""
    dm = DataModule(root=str(root), image_size=size, batch_size=batch_size, num_workers=workers,
                    gap_initial=gap, gap_final=gap, gap_warmup_steps=0, flip_augment=True,
                    train_batches_per_epoch=batches + 3)  # fmt: skip
    it = iter(dm.train_dataloader())
    for _ in range(3):  # worker start-up and the shuffle buffers
        next(it)
    start = time.perf_counter()
    n = 0
    for batch in it:
        n += batch.batch_size
    return n / (time.perf_counter() - start)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=224)
    p.add_argument("--batch-size", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batches", type=int, default=40, help="timed batches per loader case")
    p.add_argument("--scenes", type=int, default=16, help="training scenes of the benchmark set")
    p.add_argument("--gpu-steps-per-second", type=float, default=4.0)
    p.add_argument("--out", default=None, help="keep the generated data here (default: a temporary folder)")
    a = p.parse_args()
    torch.set_num_threads(2)
    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="bench_data_"))

    rows = ["| case | figure |", "| --- | --- |"]
    for frames, h, w in ((24, 64, 96), (32, 96, 128), (32, 180, 320)):
        per_scene = time_generation(work / f"gen_{h}x{w}", 4, frames, h, w)
        rows.append(f"| synthetic generation, {frames} frames at {h}x{w} | {per_scene:.2f} s / scene |")

    src = work / "src"
    generate_dataset(src, scenes=a.scenes, test_scenes=4, frames=32, height=180, width=320, seed=1)
    start = time.perf_counter()
    manifest = convert_dataset(src, work / "shards", size=a.size, workers=a.workers, progress=False)
    seconds = time.perf_counter() - start
    train = manifest["splits"]["train"]
    per_scene, rate = seconds / train["scenes"], train["samples"] / seconds
    rows.append(f"| conversion to {a.size}px shards, {a.workers} processes | {per_scene:.2f} s / scene "
                f"({rate:.0f} samples/s) |")  # fmt: skip
    gaps = json.loads((src / "dataset.json").read_text())["gap_range"]

    need = a.batch_size * a.gpu_steps_per_second
    for workers in (a.workers, 0):
        for label, gap in (
            ("all gaps allowed", tuple(gaps)),
            ("paper initial range (1 in 8 kept)", (gaps[0],) * 2),
        ):
            rate = loader_rate(work / "shards", a.size, a.batch_size, workers, a.batches, gap)
            rows.append(f"| loader, {workers} workers, {label}, {a.size}px, batch {a.batch_size} | "
                        f"{rate:.0f} samples/s ({rate / a.batch_size:.1f} batches/s) |")  # fmt: skip
    rows.append(f"| needed by a GPU at {a.gpu_steps_per_second:g} steps/s x batch {a.batch_size} | "
                f"{need:.0f} samples/s |")  # fmt: skip
    print("\n".join(rows))


if __name__ == "__main__":
    main()
