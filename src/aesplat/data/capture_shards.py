"""Posed captures -> WebDataset shards: the shard layout, manifest and checksums of the chunk path
(:mod:`aesplat.data.shards`), one shard per scene folder.

Each scene folder of the source holds a nerfstudio ``transforms.json`` or a COLMAP sparse model
(:mod:`aesplat.data.captures`). Every scene goes to one split (``test`` by default: these sets serve
evaluation). A test sample's frames come from the evaluation index (scene folder name -> context and target
frame indices, the chunk path's JSON) or, without one, from a deterministic rule: the context pair
``context_gap`` frames apart, centred in the frame order, and ``num_targets`` targets evenly spaced strictly
between; the samples drawn are written to the manifest (``evaluation_samples``) so the evaluation can be
repeated. A scene that cannot be converted is refused with a one-line reason (``manifest.json`` lists every
refused scene with it) and the others still convert. A rerun keeps every shard whose sidecar matches.
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .captures import FORMATS, CaptureError, CaptureImages, capture_cameras, read_capture
from .chunks import cameras_to_row
from .shards import MANIFEST_VERSION, ConvertConfig, make_sample, safe_key, sha256, training_views, write_tar

SPLITS = ("train", "test")


@dataclass(frozen=True)
class CaptureConfig:
    """How scene folders are read and sampled.

    fmt: ``nerfstudio`` or ``colmap``; split: where every scene goes; capture_path: the transforms file /
    model folder relative to a scene (default: found); images: the image folder (nerfstudio: replaces the
    first folder of ``file_path``; COLMAP: relative to the scene, default ``images``); frame_order:
    ``name`` or ``file`` (nerfstudio only; COLMAP frames are sorted by name); context_gap / num_targets: the
    generated evaluation sample without an index."""

    fmt: str
    split: str = "test"
    capture_path: str | None = None
    images: str | None = None
    frame_order: str = "name"
    context_gap: int = 25
    num_targets: int = 3

    def __post_init__(self) -> None:
        if self.fmt not in FORMATS:
            raise ValueError(f"unknown capture format {self.fmt!r}; choose from {FORMATS}")
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {self.split!r}")
        if self.frame_order not in ("name", "file"):
            raise ValueError(f"frame_order must be 'name' or 'file', got {self.frame_order!r}")
        if self.context_gap < 2 or self.num_targets < 1:
            raise ValueError("context_gap must be at least 2 and num_targets at least 1 (targets lie between)")


def evaluation_sample(num_frames: int, gap: int, num_targets: int) -> dict[str, Any]:
    """The deterministic test sample of a scene without an index entry: context frames ``gap`` apart centred
    in the sequence, up to ``num_targets`` distinct targets evenly spaced strictly between them."""
    c0 = (num_frames - 1 - gap) // 2
    inner = np.linspace(c0, c0 + gap, num_targets + 2)[1:-1]
    targets = sorted({int(np.clip(round(t), c0 + 1, c0 + gap - 1)) for t in inner})
    return {"context": [c0, c0 + gap], "target": targets, "overlap": None}


@dataclass(frozen=True)
class _Job:
    scene: str
    shard: str
    cfg: ConvertConfig
    capture: CaptureConfig
    indexed: bool  # an evaluation index was given (test split)
    entry: dict[str, Any] | None  # its entry for this scene (None: not in it, or null)


def _settings(job: _Job) -> dict[str, Any]:
    """What a finished shard must have been made with to be kept by a rerun."""
    return json.loads(json.dumps({"config": asdict(job.cfg), "capture": asdict(job.capture),
                                  "indexed": job.indexed, "entry": job.entry}))  # fmt: skip


def _check(capture, k: np.ndarray, job: _Job) -> None:
    """Refuse a capture the samples cannot be made from (``CaptureError``)."""
    cfg, name, frames = job.cfg, capture.key, len(capture)
    sizes = sorted({(c.width, c.height) for c in capture.cameras})
    if len(sizes) > 1:
        shown = ", ".join(f"{w}x{h}" for w, h in sizes[:4])
        raise CaptureError("mixed_image_sizes", f"{name}: frames of different sizes ({shown}); convert one "
                           "camera per scene (resize or split the capture)")  # fmt: skip
    if cfg.expect_shape is not None and (sizes[0][1], sizes[0][0]) != tuple(cfg.expect_shape):
        raise CaptureError("wrong_shape", f"{name}: images are {sizes[0][0]}x{sizes[0][1]}, --expect-shape "
                           f"says {cfg.expect_shape[1]}x{cfg.expect_shape[0]}")  # fmt: skip
    fov = np.degrees(2.0 * np.arctan(0.5 / np.stack([k[:, 0, 0], k[:, 1, 1]])))
    if (fov > cfg.max_fov_deg).any():
        raise CaptureError(
            "fov_too_wide",
            f"{name}: a field of view of {fov.max():.0f} degrees exceeds --max-fov {cfg.max_fov_deg:g}; "
            "raise it if the model should see such views",
        )
    centres = capture.c2w[:, :3, 3]
    if np.linalg.norm(centres.max(0) - centres.min(0)) < cfg.min_baseline:
        raise CaptureError("degenerate_baseline", f"{name}: the cameras move less than --min-baseline "
                           f"{cfg.min_baseline:g}; a static capture cannot be evaluated")  # fmt: skip
    if job.capture.split == "train":
        need, why = cfg.min_gap + 1, f"the smallest context gap ({cfg.min_gap}, --min-gap)"
    elif job.indexed:
        if job.entry is None:
            raise CaptureError("not_in_evaluation_index", f"{name}: no entry in the evaluation index")
        need, why = max(job.entry["context"] + job.entry["target"]) + 1, "its evaluation index entry"
    else:
        need, why = job.capture.context_gap + 1, f"a context gap of {job.capture.context_gap} (--context-gap)"
    if frames < max(need, 3):
        raise CaptureError("too_few_frames", f"{name}: {frames} frames, {why} needs {max(need, 3)}")


def _views(frames: int, c2w: np.ndarray, job: _Job, skips: Counter[str]) -> list[tuple]:
    """(sample key, context, target, overlap) of a checked scene."""
    key = safe_key(Path(job.scene).name)
    if job.capture.split == "test":
        entry = job.entry if job.indexed else evaluation_sample(frames, job.capture.context_gap,
                                                                job.capture.num_targets)  # fmt: skip
        return [(key, list(entry["context"]), list(entry["target"]), entry.get("overlap"))]
    seed = int.from_bytes(
        hashlib.sha256(f"{job.cfg.seed}/{Path(job.scene).name}".encode()).digest()[:8], "little"
    )
    out = []
    for i, (ctx, tgt) in enumerate(training_views(frames, job.cfg, np.random.default_rng(seed))):
        if np.linalg.norm(c2w[ctx[1], :3, 3] - c2w[ctx[0], :3, 3]) < job.cfg.min_baseline:
            skips["degenerate_pair"] += 1
            continue
        out.append((f"{key}_{i:03d}", ctx, tgt, None))
    return out


def convert_capture(job: _Job) -> dict[str, Any]:
    """Convert one scene folder into one shard; returns its record (also the shard's sidecar JSON). A refused
    scene writes no shard (and removes a stale one): its record carries ``refused`` and ``message``."""
    shard, name = Path(job.shard), Path(job.scene).name
    skips: Counter[str] = Counter()
    try:
        capture = read_capture(job.capture.fmt, job.scene, job.capture.capture_path, job.capture.images,
                               job.capture.frame_order)  # fmt: skip
        c2w, k = capture_cameras(capture)
        _check(capture, k, job)
        scene = {
            "key": name,
            "cameras": cameras_to_row(torch.from_numpy(c2w), torch.from_numpy(k)),
            "images": CaptureImages(capture),
        }
        views = _views(len(capture), c2w, job, skips)
        samples = [(key, make_sample(scene, ctx, tgt, ov, job.cfg)) for key, ctx, tgt, ov in views]
    except CaptureError as e:
        for stale in (shard, shard.with_suffix(".json")):
            stale.unlink(missing_ok=True)
        message = str(e) if str(e).startswith(f"{name}:") else f"{name}: {e}"
        return {"scene": name, "refused": e.reason, "message": message}
    write_tar(shard, samples)
    record = {
        "shard": shard.name,
        "scene": name,
        "chunk": name,  # the source unit, as the chunk path names it
        "samples": len(samples),
        "scenes": 1,
        "scenes_seen": 1,
        "scene_keys": [name],
        "frames": len(capture),
        "skips": dict(sorted(skips.items())),
        "evaluation_sample": _stated(capture.names, views[0]) if job.capture.split == "test" else None,
        "sha256": sha256(shard),
        "bytes": shard.stat().st_size,
        **_settings(job),
    }
    shard.with_suffix(".json").write_text(json.dumps(record, indent=1))
    return record


def _stated(names: list[str], view: tuple) -> dict[str, Any]:
    """A test sample as the manifest states it: an evaluation index entry, plus the files it reads."""
    _, context, target, _ = view
    return {"context": context, "target": target, "files": [names[f] for f in context + target]}


def _finished(job: _Job) -> dict[str, Any] | None:
    """The sidecar record if the scene's shard was made with the same settings and still matches it."""
    shard = Path(job.shard)
    sidecar = shard.with_suffix(".json")
    if not (shard.exists() and sidecar.exists()):
        return None
    try:
        record = json.loads(sidecar.read_text())
    except json.JSONDecodeError:
        return None
    same = all(record.get(k) == v for k, v in _settings(job).items())
    return record if same and record.get("sha256") == sha256(shard) else None


def convert_captures(
    src: str | Path,
    out: str | Path,
    fmt: str,
    size: int = ConvertConfig.size,
    split: str = "test",
    eval_index: str | Path | None = None,
    workers: int = 1,
    capture_path: str | None = None,
    images: str | None = None,
    frame_order: str = "name",
    context_gap: int = CaptureConfig.context_gap,
    num_targets: int = CaptureConfig.num_targets,
    min_gap: int = ConvertConfig.min_gap,
    max_gap: int = ConvertConfig.max_gap,
    samples_per_scene: int = ConvertConfig.samples_per_scene,
    train_targets: int = ConvertConfig.train_targets,
    max_fov_deg: float = ConvertConfig.max_fov_deg,
    min_baseline: float = ConvertConfig.min_baseline,
    expect_shape: tuple[int, int] | None = None,
    jpeg_quality: int = ConvertConfig.jpeg_quality,
    seed: int = ConvertConfig.seed,
    dataset: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Convert ``src/<scene>/`` capture folders into ``out/<split>/<split>-<scene>.tar`` and
    ``out/manifest.json``; the options are :class:`CaptureConfig`'s and the chunk path's
    (:func:`aesplat.data.shards.convert_dataset`). eval_index defaults to ``src/evaluation_index.json`` if it
    exists (test split). Returns the manifest."""
    src, out = Path(src), Path(out)
    capture = CaptureConfig(fmt, split, capture_path, images, frame_order, context_gap, num_targets)
    if not src.is_dir():
        raise FileNotFoundError(f"{src} is not a folder; --src must hold one folder per scene")
    scenes = sorted(p for p in src.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not scenes:
        raise FileNotFoundError(f"{src} holds no scene folder; --src must hold one folder per scene")
    cfg = ConvertConfig(size=size, min_gap=min_gap, max_gap=max_gap, samples_per_scene=samples_per_scene,
                        train_targets=train_targets, max_fov_deg=max_fov_deg, min_baseline=min_baseline,
                        expect_shape=tuple(expect_shape) if expect_shape is not None else None,
                        jpeg_quality=jpeg_quality, seed=seed, dataset=dataset or src.name)  # fmt: skip
    if eval_index is None and split == "test" and (src / "evaluation_index.json").is_file():
        eval_index = src / "evaluation_index.json"  # as the chunk path does
    index = None
    if eval_index is not None:
        if split != "test":
            raise ValueError("--eval-index picks test samples; it needs --split test")
        index = json.loads(Path(eval_index).read_text())
    shard_names = Counter(safe_key(p.name) for p in scenes)
    clashes = sorted(n for n, c in shard_names.items() if c > 1)
    if clashes:
        raise ValueError(
            f"scene folders {clashes} differ only in characters a shard name cannot hold; rename them"
        )

    (out / split).mkdir(parents=True, exist_ok=True)
    jobs, records = [], []
    for scene in scenes:
        entry = index.get(scene.name) if index is not None else None
        job = _Job(str(scene), str(out / split / f"{split}-{safe_key(scene.name)}.tar"), cfg, capture,
                   index is not None, entry)  # fmt: skip
        done = _finished(job)
        if done is not None:
            records.append(done)
        else:
            jobs.append(job)

    from tqdm import tqdm

    with tqdm(total=len(jobs), desc="scenes", disable=not progress) as bar:
        if workers > 1 and len(jobs) > 1:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for record in pool.map(convert_capture, jobs):
                    records.append(record)
                    bar.update()
        else:
            for job in jobs:
                records.append(convert_capture(job))
                bar.update()

    records.sort(key=lambda r: r["scene"])
    made = [r for r in records if "refused" not in r]
    refused = {r["scene"]: r["message"] for r in records if "refused" in r}
    skips: Counter[str] = Counter(r["refused"] for r in records if "refused" in r)
    for r in made:
        skips.update(r["skips"])
    entry: dict[str, Any] = {
        "samples": sum(r["samples"] for r in made),
        "scenes": len(made),
        "scenes_seen": len(records),
        "skips": dict(sorted(skips.items())),
        "refused": refused,
        "shards": [{k: r[k] for k in ("shard", "chunk", "samples", "scenes", "sha256", "bytes")} for r in made],
    }
    if index is not None:
        wanted = {k for k, v in index.items() if v is not None}
        entry["evaluation_index_entries"] = len(wanted)
        entry["evaluation_index_missing"] = len(wanted - {r["scene"] for r in made})
    manifest: dict[str, Any] = {
        "version": MANIFEST_VERSION,
        "source": str(src),
        "config": asdict(cfg),
        "capture": asdict(capture),
        "evaluation_index": str(eval_index) if eval_index is not None else None,
        "evaluation_samples": {r["scene"]: r["evaluation_sample"] for r in made if r.get("evaluation_sample")},
        "splits": {split: entry},
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest
