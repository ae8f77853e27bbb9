"""Chunk -> WebDataset shard conversion (docs/data.md).

One source chunk becomes one tar shard per split, written to a temporary name and renamed when complete, with
a sidecar ``*.json`` (counts, skips, SHA-256). A rerun skips every shard whose sidecar matches its tar, so an
interrupted conversion resumes. ``manifest.json`` gathers the sidecars. A chunk that yields no sample (corrupt,
or every scene skipped) writes no shard; corrupt chunks and skipped scenes are named on stderr as well as
counted in the manifest.

Sample layout (V = context views first, then targets)::

    KEY.ctx0.jpg ... KEY.tgt0.jpg ...   square JPEGs, centre-cropped then resized
    KEY.extrinsics.npy   float32 [V, 4, 4] camera-to-world in the source scene's world frame
    KEY.intrinsics.npy   float32 [V, 3, 3] normalised, for the cropped image
    KEY.meta.json        {"scene", "dataset", "context", "target", "gap", "overlap"}
    KEY.tgt0.spec.png …  test and validation samples of scenes whose chunk entry carries ``specular`` only:
                         8-bit mask per target, 255 where the specular term exceeds ``specular_threshold``.
                         The magnitude is cropped like the image, area-resampled (box filter) to the output
                         size, then thresholded: a pixel is a highlight when the mean term over it exceeds it.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import sys
import tarfile
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ..errors import MissingFileError
from .chunks import jpeg_bytes, list_chunks, load_chunk, row_to_cameras

MANIFEST_VERSION = 1


@dataclass(frozen=True)
class ConvertConfig:
    """Options of the conversion (the ``to_shards.py`` flags).

    size: output side in pixels; min_gap / max_gap: context-gap range of training samples (frames);
    samples_per_scene: training samples per scene; train_targets: targets per training sample (drawn strictly
    between the context frames); max_fov_deg: skip scenes with a wider horizontal or vertical FOV;
    min_baseline: skip scenes whose camera centres span less (and training pairs closer) than this;
    expect_shape: (H, W) every source image must have, or None to accept any consistent shape;
    specular_threshold: a test target's pixel is a highlight (``tgtI.spec.png``) where the scene's specular
    term exceeds this.
    """

    size: int = 256
    min_gap: int = 25
    max_gap: int = 90
    samples_per_scene: int = 8
    train_targets: int = 3
    max_fov_deg: float = 100.0
    min_baseline: float = 1e-3
    expect_shape: tuple[int, int] | None = None
    jpeg_quality: int = 95
    seed: int = 0
    dataset: str = "unknown"
    specular_threshold: float = 0.05

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"size must be a positive number of pixels, got {self.size}")
        if not 2 <= self.min_gap <= self.max_gap:  # a target must fit strictly between the context frames
            raise ValueError(f"need 2 <= min_gap <= max_gap, got {self.min_gap}, {self.max_gap}")
        if self.samples_per_scene < 1 or self.train_targets < 1:
            raise ValueError("samples_per_scene and train_targets must be at least 1")
        if not self.specular_threshold >= 0.0:
            raise ValueError(f"specular_threshold must be >= 0, got {self.specular_threshold}")


def safe_key(text: str) -> str:
    """A WebDataset key: no dots (they separate the extension) and no path separators."""
    return re.sub(r"[^A-Za-z0-9_\-]", "_", text)


# ----------------------------------------------------------------------------------------------- images


def square_crop_box(width: int, height: int) -> tuple[int, int, int, int]:
    """The centred square of the shorter side (integer offsets), as PIL's (left, top, right, bottom)."""
    side = min(width, height)
    left, top = (width - side) // 2, (height - side) // 2
    return left, top, left + side, top + side


def crop_resize(jpeg: bytes, size: int, intrinsics: np.ndarray) -> tuple[Image.Image, np.ndarray]:
    """Centre-crop a JPEG to a square of its shorter side (integer offset), then resize to ``size``.

    intrinsics [3, 3] normalised for the full image -> normalised for the output. Resizing maps the crop's
    extent onto the output's, so normalised coordinates are unchanged by it; only the crop moves them.
    """
    image = Image.open(io.BytesIO(jpeg)).convert("RGB")
    w, h = image.size
    left, top, right, bottom = square_crop_box(w, h)
    side = right - left
    image = image.crop((left, top, right, bottom)).resize((size, size), Image.Resampling.BICUBIC)
    k = intrinsics.astype(np.float64).copy()
    k[0, 0], k[0, 2] = k[0, 0] * w / side, (k[0, 2] * w - left) / side
    k[1, 1], k[1, 2] = k[1, 1] * h / side, (k[1, 2] * h - top) / side
    return image, k


def highlight_mask(specular: np.ndarray, size: int, threshold: float) -> np.ndarray:
    """Specular magnitude [H, W] of a full frame -> bool mask [size, size] of the output image's pixels whose
    mean magnitude (area resampling of the same centre crop as the image) exceeds ``threshold``."""
    magnitude = Image.fromarray(np.asarray(specular, dtype=np.float32), mode="F")
    cropped = magnitude.crop(square_crop_box(*magnitude.size))
    return np.asarray(cropped.resize((size, size), Image.Resampling.BOX)) > threshold


def _png(mask: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(mask.astype(np.uint8) * 255, mode="L").save(buf, format="PNG")
    return buf.getvalue()


def _encode(image: Image.Image, quality: int) -> bytes:
    buf = io.BytesIO()
    image.save(buf, format="JPEG", quality=quality, subsampling=0)  # 4:4:4: small images keep their colour
    return buf.getvalue()


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------- samples


def validate_scene(scene: dict[str, Any], cfg: ConvertConfig) -> str | None:
    """The reason to skip a scene (``"missing_field"``, ``"too_few_frames"``, ``"bad_camera"``,
    ``"corrupt_image"``, ``"wrong_shape"``, ``"fov_too_wide"``, ``"degenerate_baseline"``) or None."""
    if not all(k in scene for k in ("key", "cameras", "images")):
        return "missing_field"
    cams = np.asarray(scene["cameras"], dtype=np.float64)
    if cams.ndim != 2 or cams.shape[1] != 18 or cams.shape[0] != len(scene["images"]):
        return "bad_camera"
    if cams.shape[0] < 3:
        return "too_few_frames"
    if not np.isfinite(cams).all() or (cams[:, :2] <= 0).any():
        return "bad_camera"
    shapes = set()
    for image in scene["images"]:  # header reads only: cheap
        try:
            with Image.open(io.BytesIO(jpeg_bytes(image))) as im:
                shapes.add((im.height, im.width))
        except Exception:  # noqa: BLE001 - any unreadable header means a corrupt image
            return "corrupt_image"
    if len(shapes) != 1 or (cfg.expect_shape is not None and shapes != {tuple(cfg.expect_shape)}):
        return "wrong_shape"
    fov = 2.0 * np.degrees(np.arctan(0.5 / cams[:, :2]))
    if (fov > cfg.max_fov_deg).any():
        return "fov_too_wide"
    c2w, _ = row_to_cameras(cams)
    centres = c2w[:, :3, 3]
    if np.linalg.norm(centres.max(0) - centres.min(0)) < cfg.min_baseline:
        return "degenerate_baseline"
    return None


def training_views(
    num_frames: int, cfg: ConvertConfig, rng: np.random.Generator
) -> list[tuple[list[int], list[int]]]:
    """Context / target frame ids of the training samples of one scene.

    Gaps are stratified over [min_gap, max_gap] (clipped to the scene's length, which must exceed min_gap)
    so every scene covers the whole curriculum range; the first sample always uses the smallest gap. Up to
    ``train_targets`` targets lie strictly between the context frames.
    """
    lo, hi = cfg.min_gap, min(cfg.max_gap, num_frames - 1)
    if hi < lo:
        raise ValueError(f"a scene of {num_frames} frames has no context gap of at least {lo}")
    n = cfg.samples_per_scene
    edges = np.linspace(lo, hi + 1, n + 1)
    views = []
    for i in range(n):
        gap = lo if i == 0 else int(np.clip(np.floor(rng.uniform(edges[i], edges[i + 1])), lo, hi))
        c0 = int(rng.integers(0, num_frames - gap))
        between = np.arange(c0 + 1, c0 + gap)
        targets = sorted(
            int(t) for t in rng.choice(between, size=min(cfg.train_targets, len(between)), replace=False)
        )
        views.append(([c0, c0 + gap], targets))
    return views


def make_sample(scene: dict[str, Any], context: list[int], target: list[int], overlap: float | None,
                cfg: ConvertConfig, highlights: bool = False) -> dict[str, bytes]:  # fmt: skip
    """One shard sample (extension -> bytes) from a source scene and its frame ids. ``highlights``: also write
    each target's highlight mask (``tgtI.spec.png``) if the scene carries its specular magnitude."""
    c2w, k = row_to_cameras(scene["cameras"])
    frames = list(context) + list(target)
    names = [f"ctx{i}.jpg" for i in range(len(context))] + [f"tgt{i}.jpg" for i in range(len(target))]
    sample: dict[str, bytes] = {}
    intrinsics = []
    for name, f in zip(names, frames):
        image, k_crop = crop_resize(jpeg_bytes(scene["images"][f]), cfg.size, k[f])
        sample[name] = _encode(image, cfg.jpeg_quality)
        intrinsics.append(k_crop)
    meta = {
        "scene": str(scene["key"]),
        "dataset": cfg.dataset,
        "context": [int(f) for f in context],
        "target": [int(f) for f in target],
        "gap": int(context[-1] - context[0]),
        "overlap": None if overlap is None or not math.isfinite(overlap) else float(overlap),
    }
    if highlights and scene.get("specular") is not None:
        magnitude = np.asarray(scene["specular"], dtype=np.float32)  # [F, H, W] (stored as float16)
        if magnitude.shape[0] != len(scene["images"]):
            raise ValueError(f"specular holds {magnitude.shape[0]} frames, the scene {len(scene['images'])}")
        for i, f in enumerate(target):
            sample[f"tgt{i}.spec.png"] = _png(highlight_mask(magnitude[f], cfg.size, cfg.specular_threshold))
    sample["extrinsics.npy"] = _npy(c2w[frames].astype(np.float32))
    sample["intrinsics.npy"] = _npy(np.stack(intrinsics).astype(np.float32))
    sample["meta.json"] = json.dumps(meta).encode()
    return sample


def write_tar(path: Path, samples: list[tuple[str, dict[str, bytes]]]) -> None:
    """Write samples [(key, {ext: bytes})] as a WebDataset tar (fixed mtime: reproducible checksums), under a
    temporary name (``*.tar.tmp``) renamed to ``path`` once complete: a reader never sees half a shard."""
    tmp = Path(path).with_suffix(".tar.tmp")
    with tarfile.open(tmp, "w", format=tarfile.USTAR_FORMAT) as tar:
        for key, sample in samples:
            for ext, data in sample.items():
                info = tarfile.TarInfo(f"{key}.{ext}")
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                tar.addfile(info, io.BytesIO(data))
    os.replace(tmp, path)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class _Job:
    split: str
    chunk: str
    shard: str
    cfg: ConvertConfig
    eval_index: dict[str, Any] | None  # held-out splits only; None = sample like training but deterministically
    held_out: frozenset[str] = frozenset()  # train split: scenes kept for validation (left out here)
    only: frozenset[str] | None = None  # validation held out of train: convert these scenes of the chunk only


def _scene_samples(scene: dict[str, Any], key: str, job: _Job, skips: Counter[str]) -> list[tuple]:
    """(sample key, context ids, target ids, overlap) of one valid scene: the evaluation index's entry, or
    the training draw (seeded by the scene key, so a resumed or re-run conversion draws the same samples)."""
    if job.eval_index is not None:
        entry = job.eval_index[key]
        return [(safe_key(key), list(entry["context"]), list(entry["target"]), entry.get("overlap"))]
    seed = int.from_bytes(hashlib.sha256(f"{job.cfg.seed}/{key}".encode()).digest()[:8], "little")
    views = training_views(len(scene["images"]), job.cfg, np.random.default_rng(seed))
    centres = row_to_cameras(scene["cameras"])[0][:, :3, 3]
    out = []
    for i, (ctx, tgt) in enumerate(views):
        if np.linalg.norm(centres[ctx[1]] - centres[ctx[0]]) < job.cfg.min_baseline:
            skips["degenerate_pair"] += 1
            continue
        out.append((f"{safe_key(key)}_{i:03d}", ctx, tgt, None))
    return out


def convert_chunk(job: _Job) -> dict[str, Any]:
    """Convert one chunk into one shard; returns its record (also written as the shard's sidecar JSON)."""
    shard = Path(job.shard)
    skips: Counter[str] = Counter()
    samples: list[tuple[str, dict[str, bytes]]] = []
    scenes_seen = 0
    used_keys: list[str] = []
    skipped: list[tuple[str, str]] = []  # (scene key, reason); a corrupt chunk: ("", the error)
    try:
        chunk = load_chunk(job.chunk)
    except ValueError as err:
        chunk, skips["corrupt_chunk"] = [], 1
        skipped.append(("", str(err).splitlines()[0]))
    for scene in chunk:
        scenes_seen += 1
        reason = validate_scene(scene, job.cfg) if isinstance(scene, dict) else "missing_field"
        key = str(scene.get("key", "")) if isinstance(scene, dict) else ""
        if key in job.held_out or (job.only is not None and key not in job.only):
            scenes_seen -= 1  # the other split's scene: neither seen nor skipped here
            continue
        if reason is None and job.eval_index is None and len(scene["images"]) <= job.cfg.min_gap:
            reason = "shorter_than_min_gap"
        if reason is None and job.eval_index is not None:
            entry = job.eval_index.get(key)
            if entry is None:
                reason = "not_in_evaluation_index"
            elif max(entry["context"] + entry["target"]) >= len(scene["images"]):
                reason = "evaluation_frames_out_of_range"
        if reason is not None:
            skips[reason] += 1
            skipped.append((key or f"#{scenes_seen - 1}", reason))
            continue
        try:
            made = [(name, make_sample(scene, ctx, tgt, ov, job.cfg, highlights=job.split != "train"))
                    for name, ctx, tgt, ov in _scene_samples(scene, key, job, skips)]  # fmt: skip
        except Exception:  # noqa: BLE001 - a broken frame skips its scene, never the run
            skips["corrupt_image"] += 1
            skipped.append((key, "corrupt_image"))
            continue
        samples.extend(made)
        used_keys.append(key)
    highlight, masked = _highlight_pixels(samples)
    record = {
        "shard": shard.name if samples else None,  # no sample, no shard (and no sidecar: a rerun retries it)
        "chunk": Path(job.chunk).name,
        "samples": len(samples),
        "scenes": len(used_keys),
        "scenes_seen": scenes_seen,
        "scene_keys": used_keys,
        "skips": dict(sorted((k, v) for k, v in skips.items() if v)),
        "skipped_scenes": [list(item) for item in skipped],
        "sha256": None,
        "bytes": 0,
        "highlight_pixels": highlight,
        "masked_target_pixels": masked,
        "config": asdict(job.cfg),
        "evaluation_index_sha256": _index_digest(job.eval_index),
        "held_out_sha256": _keys_digest(job),
    }
    if not samples:
        shard.unlink(missing_ok=True)  # a shard of an earlier conversion of this chunk is stale now
        shard.with_suffix(".json").unlink(missing_ok=True)
        return record
    write_tar(shard, samples)
    record.update(sha256=sha256(shard), bytes=shard.stat().st_size)
    shard.with_suffix(".json").write_text(json.dumps(record, indent=1))
    return record


def report_skips(split: str, record: dict[str, Any]) -> None:
    """Name on stderr what a chunk's conversion left out: the chunk itself if corrupt, else each scene."""
    for key, reason in record.get("skipped_scenes", []):
        if key:
            print(f"to_shards: {split}/{record['chunk']}: scene {key} skipped ({reason})", file=sys.stderr)
        else:
            print(f"to_shards: {split}/{record['chunk']}: corrupt chunk, no shard written ({reason})",
                  file=sys.stderr)  # fmt: skip
    if not record.get("skipped_scenes") and not record["samples"]:
        print(f"to_shards: {split}/{record['chunk']}: no sample, no shard written", file=sys.stderr)


def _highlight_pixels(samples: list[tuple[str, dict[str, bytes]]]) -> tuple[int, int]:
    """(highlight pixels, pixels of targets with a mask) over the samples' ``tgtI.spec.png`` masks."""
    highlight = total = 0
    for _, sample in samples:
        for ext, data in sample.items():
            if ext.endswith(".spec.png"):
                with Image.open(io.BytesIO(data)) as im:
                    mask = np.asarray(im) > 0
                highlight, total = highlight + int(mask.sum()), total + mask.size
    return highlight, total


def _index_digest(index: dict[str, Any] | None) -> str | None:
    return None if index is None else hashlib.sha256(json.dumps(index, sort_keys=True).encode()).hexdigest()


def _keys_digest(job: _Job) -> str | None:
    """Digest of the scenes a job leaves out or keeps (None when it converts the whole chunk)."""
    if not job.held_out and job.only is None:
        return None
    text = json.dumps([sorted(job.held_out), None if job.only is None else sorted(job.only)])
    return hashlib.sha256(text.encode()).hexdigest()


def held_out_keys(keys: list[str], count: int, seed: int) -> list[str]:
    """The ``count`` training scenes held out for validation: the keys ranked by a hash of the conversion
    seed and the key, so the choice depends on neither the chunk order nor the number of workers. Sorted."""
    if not 0 <= count < len(keys):
        raise ValueError(
            f"--val-scenes {count}: need 0 <= N < the {len(keys)} training scenes (leave some to train on)"
        )
    rank = sorted(keys, key=lambda k: hashlib.sha256(f"{seed}/validation/{k}".encode()).hexdigest())
    return sorted(rank[:count])


def _chunk_keys(split_dir: Path) -> dict[str, str]:
    """Scene key -> chunk file name of a split: its ``index.json``, else read from every chunk."""
    index_file = split_dir / "index.json"
    if index_file.exists():
        return json.loads(index_file.read_text())
    out = {}
    for chunk in list_chunks(split_dir):
        try:
            scenes = load_chunk(chunk)
        except ValueError:
            continue  # the train job reports it as a corrupt chunk
        out.update({str(s["key"]): chunk.name for s in scenes if isinstance(s, dict) and "key" in s})
    return out


def _done(shard: Path, job: _Job) -> dict[str, Any] | None:
    """The sidecar record if ``shard`` was completed with the same options and evaluation index and its
    checksum still matches."""
    sidecar = shard.with_suffix(".json")
    if not (shard.exists() and sidecar.exists()):
        return None
    try:
        record = json.loads(sidecar.read_text())
    except json.JSONDecodeError:
        return None
    same_options = record.get("config") == json.loads(json.dumps(asdict(job.cfg)))
    same_index = record.get("evaluation_index_sha256") == _index_digest(job.eval_index)
    same_index = same_index and record.get("held_out_sha256") == _keys_digest(job)
    if not (same_options and same_index) or record.get("sha256") != sha256(shard):
        return None
    return record


def convert_dataset(
    src: str | Path,
    out: str | Path,
    size: int = ConvertConfig.size,
    eval_index: str | Path | None = None,
    workers: int = 1,
    min_gap: int | None = None,
    max_gap: int | None = None,
    samples_per_scene: int = ConvertConfig.samples_per_scene,
    train_targets: int = ConvertConfig.train_targets,
    max_fov_deg: float = ConvertConfig.max_fov_deg,
    min_baseline: float = ConvertConfig.min_baseline,
    expect_shape: tuple[int, int] | None = None,
    jpeg_quality: int = ConvertConfig.jpeg_quality,
    seed: int = ConvertConfig.seed,
    dataset: str | None = None,
    specular_threshold: float = ConvertConfig.specular_threshold,
    progress: bool = True,
    val_scenes: int = 0,
    val_index: str | Path | None = None,
) -> dict[str, Any]:
    """Convert ``src/{train,validation,test}`` chunk folders into ``out/<split>/*.tar`` and
    ``out/manifest.json``.

    eval_index: the evaluation index JSON for the test split (default ``src/evaluation_index.json`` if it
    exists; without one the test split is sampled like training, deterministically, one sample per scene).
    val_index: the same for the validation split (default ``src/validation_index.json``).
    val_scenes: for a source without a validation split (RealEstate10K, ACID), hold this many training scenes
    out as the validation split (``held_out_keys``: deterministic); the manifest lists them. The remaining
    training scenes' shards are converted as before, without them.
    min_gap / max_gap default to ``src/dataset.json``'s ``gap_range`` if present, else the paper's 25 / 90.
    Test samples of scenes that carry their specular magnitude get highlight masks (``specular_threshold``);
    the manifest's test entry then states their ``highlight_share`` of target pixels.
    Already completed shards (sidecar checksum matches) are kept: an interrupted run resumes.
    Returns the manifest.
    """
    src, out = Path(src), Path(out)
    splits = [s for s in ("train", "validation", "test") if (src / s).is_dir()]
    if not splits:
        raise MissingFileError(f"{src} holds no train/ or test/ folder of *.torch chunks (pixelSplat layout)")
    held: list[str] = []
    if val_scenes:
        if "validation" in splits:
            raise ValueError(f"{src} already has a validation/ split; drop --val-scenes (it holds out training "
                             "scenes only for sources without one)")  # fmt: skip
        if "train" not in splits:
            raise ValueError(f"--val-scenes holds out training scenes, but {src} has no train/ folder")
        keys = _chunk_keys(src / "train")
        held = held_out_keys(sorted(keys), val_scenes, seed)
        splits.insert(1, "validation")
    info = json.loads((src / "dataset.json").read_text()) if (src / "dataset.json").exists() else {}
    gaps = info.get("gap_range", [ConvertConfig.min_gap, ConvertConfig.max_gap])
    base = ConvertConfig(
        size=size,
        min_gap=min_gap if min_gap is not None else int(gaps[0]),
        max_gap=max_gap if max_gap is not None else int(gaps[1]),
        samples_per_scene=samples_per_scene,
        train_targets=train_targets,
        max_fov_deg=max_fov_deg,
        min_baseline=min_baseline,
        expect_shape=tuple(expect_shape) if expect_shape is not None else None,
        jpeg_quality=jpeg_quality,
        seed=seed,
        dataset=dataset or info.get("dataset", src.name),
        specular_threshold=specular_threshold,
    )
    if eval_index is None and (src / "evaluation_index.json").exists():
        eval_index = src / "evaluation_index.json"
    index = json.loads(Path(eval_index).read_text()) if eval_index is not None else None
    if val_index is None and (src / "validation_index.json").exists() and "validation" in splits and not held:
        val_index = src / "validation_index.json"
    vindex = json.loads(Path(val_index).read_text()) if val_index is not None else None
    indexes = {"train": None, "validation": vindex, "test": index}
    held_set = frozenset(held)
    held_chunks = {keys[k] for k in held}

    jobs, records = [], []
    for split in splits:
        (out / split).mkdir(parents=True, exist_ok=True)
        from_train = split == "validation" and bool(held)
        chunks = list_chunks(src / ("train" if from_train else split))
        for chunk in chunks:
            if from_train and chunk.name not in held_chunks:
                continue
            shard = out / split / f"{split}-{chunk.stem}.tar"
            ev = indexes[split]
            cfg = (
                ConvertConfig(**{**asdict(base), "samples_per_scene": 1})
                if split != "train" and ev is None
                else base
            )
            job = _Job(split, str(chunk), str(shard), cfg, ev, held_out=held_set if split == "train" else
                       frozenset(), only=held_set if from_train else None)  # fmt: skip
            done = _done(shard, job)
            if done is not None:
                records.append((split, done))
            else:
                jobs.append((split, job))

    from tqdm import tqdm

    with tqdm(total=len(jobs), desc="shards", disable=not progress) as bar:
        if workers > 1 and len(jobs) > 1:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for (split, _), record in zip(jobs, pool.map(convert_chunk, [j for _, j in jobs])):
                    records.append((split, record))
                    report_skips(split, record)
                    bar.update()
        else:
            for split, job in jobs:
                records.append((split, convert_chunk(job)))
                report_skips(split, records[-1][1])
                bar.update()

    manifest: dict[str, Any] = {
        "version": MANIFEST_VERSION,
        "source": str(src),
        "config": asdict(base),
        "evaluation_index": str(eval_index) if eval_index else None,
        "validation_index": str(val_index) if val_index else None,
        "splits": {},
    }
    for split in splits:
        recs = sorted((r for s, r in records if s == split), key=lambda r: r["chunk"])
        skips: Counter[str] = Counter()
        for r in recs:
            skips.update(r["skips"])
        entry = {
            "samples": sum(r["samples"] for r in recs),
            "scenes": sum(r["scenes"] for r in recs),
            "scenes_seen": sum(r["scenes_seen"] for r in recs),
            "skips": dict(sorted(skips.items())),
            "shards": [
                {k: r[k] for k in ("shard", "chunk", "samples", "scenes", "sha256", "bytes")}
                for r in recs
                if r["shard"] is not None
            ],
        }
        masked = sum(r.get("masked_target_pixels", 0) for r in recs)
        if masked:  # share of target pixels marked as highlights (tgtI.spec.png), at the output size
            entry["highlight_share"] = sum(r.get("highlight_pixels", 0) for r in recs) / masked
        if indexes[split] is not None:
            wanted = {k for k, v in indexes[split].items() if v is not None}
            found = {k for r in recs for k in r["scene_keys"]}
            entry["evaluation_index_entries"] = len(wanted)
            entry["evaluation_index_missing"] = len(wanted - found)
        if split == "validation" and held:  # which training scenes became the validation split, and how
            entry["held_out_from_train"] = {"count": len(held), "seed": seed, "scene_keys": held}
        manifest["splits"][split] = entry
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def verify_shards(out: str | Path) -> list[str]:
    """Shards whose SHA-256 no longer matches the manifest (or that are missing), as relative paths."""
    out = Path(out)
    if not (out / "manifest.json").is_file():
        raise MissingFileError(
            f"no manifest.json in {out}: nothing to verify (convert first: to_shards.py --src SRC --out {out})"
        )
    manifest = json.loads((out / "manifest.json").read_text())
    bad = []
    for split, entry in manifest["splits"].items():
        for shard in entry["shards"]:
            path = out / split / shard["shard"]
            if not path.exists() or sha256(path) != shard["sha256"]:
                bad.append(f"{split}/{shard['shard']}")
    return bad
