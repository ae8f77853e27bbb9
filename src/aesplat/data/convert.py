"""The conversion: any source reader's scenes -> WebDataset shards and ``manifest.json`` (docs/data.md).

Every unit of the source (a chunk file, a scene folder) becomes one shard per split, written under a temporary
name, synced and renamed when complete, with a sidecar ``*.json`` (counts, skips with reasons, SHA-256, the
options and the source files it was made from). A rerun keeps a shard only when its sidecar matches the options,
its checksum still matches and none of its source files changed (size and modification time); otherwise it is
made again, so an interrupted conversion resumes and a changed source is never served stale. ``manifest.json``
(:mod:`aesplat.data.manifest`) gathers the sidecars. Every scene passes the one validation layer
(:func:`aesplat.data.validate.check_scene`); what it refuses is counted by reason and named on stderr. The
samples' members are those of :mod:`aesplat.data.layout`.
"""

from __future__ import annotations

import hashlib
import io
import json
import sys
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ..errors import UserError
from ..files import atomic_write, remove_partials
from .layout import (
    EXTRINSICS,
    FRAME_OFFSETS,
    FRAMES,
    INTRINSICS,
    META,
    evaluation_stems,
    highlight_member,
    image_member,
    safe_key,
)
from .manifest import MANIFEST_VERSION, sha256
from .sampler import evaluation_context, evaluation_sample
from .scene import Scene, SceneError, Skipped
from .sources import Reader, SourceConfig, Unit, make_reader
from .tar_files import ShardWriter
from .validate import EvaluationEntry, check_scene, read_evaluation_index


@dataclass(frozen=True)
class ConvertConfig:
    """Options of the writer (the ``to_shards.py`` flags), the same for every source format.

    size: output side in pixels; min_gap: training scenes need more frames than this (the smallest context gap
    of the curriculum; default: the source's ``dataset.json``, else 25); frame_stride: training scenes keep
    every n-th frame (gaps then count stored frames); max_fov_deg: refuse scenes with a wider horizontal or
    vertical FOV; min_baseline: refuse scenes whose camera centres span less; expect_shape: (H, W) every
    source image must have, or None; context_gap / num_targets: the evaluation sample of a scene without an
    index (default context_gap: min_gap); eval_context_views: evaluation samples carry the contexts of
    k = 2 .. this many views; specular_threshold: a target pixel is a highlight (``tgtI.spec.png``) where the
    scene's specular term exceeds this; seed: which training scenes ``--val-scenes`` holds out.
    """

    size: int = 256
    min_gap: int = 25
    frame_stride: int = 1
    max_fov_deg: float = 100.0
    min_baseline: float = 1e-3
    expect_shape: tuple[int, int] | None = None
    jpeg_quality: int = 95
    seed: int = 0
    context_gap: int = 25
    num_targets: int = 3
    eval_context_views: int = 6
    specular_threshold: float = 0.05

    def __post_init__(self) -> None:
        if self.size < 1:
            raise UserError(f"size must be a positive number of pixels, got {self.size}")
        if self.min_gap < 2 or self.context_gap < 2:  # a target must fit strictly between the context frames
            raise UserError(
                f"min_gap and context_gap must be at least 2, got {self.min_gap}, {self.context_gap}"
            )
        if self.frame_stride < 1 or self.num_targets < 1 or self.eval_context_views < 2:
            raise UserError("frame_stride and num_targets must be at least 1, eval_context_views at least 2")
        if not 1 <= self.jpeg_quality <= 100:
            raise UserError(f"jpeg_quality must lie in 1..100, got {self.jpeg_quality}")
        if not self.specular_threshold >= 0.0:
            raise UserError(f"specular_threshold must be >= 0, got {self.specular_threshold}")


# ----------------------------------------------------------------------------------------------- images


def square_crop_box(width: int, height: int) -> tuple[int, int, int, int]:
    """The centred square of the shorter side (integer offsets), as PIL's (left, top, right, bottom)."""
    side = min(width, height)
    left, top = (width - side) // 2, (height - side) // 2
    return left, top, left + side, top + side


def crop_resize(data: bytes, size: int, intrinsics: np.ndarray) -> tuple[Image.Image, np.ndarray]:
    """Centre-crop an encoded image to a square of its shorter side (integer offset), then resize to ``size``.

    intrinsics [3, 3] normalised for the full image -> normalised for the output. Resizing maps the crop's
    extent onto the output's, so normalised coordinates are unchanged by it; only the crop moves them.
    """
    image = Image.open(io.BytesIO(data)).convert("RGB")
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


def _jpeg(image: Image.Image, quality: int) -> bytes:
    buf = io.BytesIO()
    image.save(buf, format="JPEG", quality=quality, subsampling=0)  # 4:4:4: small images keep their colour
    return buf.getvalue()


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _frames(scene: Scene, frames: list[int], cfg: ConvertConfig) -> tuple[list[bytes], np.ndarray]:
    """The frames cropped, resized and encoded, and their intrinsics for the crop [V, 3, 3]."""
    images, ks = [], []
    for f in frames:
        image, k = crop_resize(scene.images[f], cfg.size, scene.intrinsics[f])
        images.append(_jpeg(image, cfg.jpeg_quality))
        ks.append(k)
    return images, np.stack(ks)


# ----------------------------------------------------------------------------------------------- samples


def scene_sample(scene: Scene, cfg: ConvertConfig) -> dict[str, bytes]:
    """A training shard sample: the whole scene (every ``frame_stride``-th frame), meta first."""
    frames = list(range(0, len(scene), cfg.frame_stride))
    images, ks = _frames(scene, frames, cfg)
    meta = {"scene": scene.key, "dataset": scene.dataset, "frames": frames, "layout": "scene"}
    sample = {META: json.dumps(meta).encode()}
    sample[EXTRINSICS] = _npy(scene.c2w[frames].astype(np.float32))
    sample[INTRINSICS] = _npy(ks.astype(np.float32))
    sample[FRAME_OFFSETS] = _npy(np.cumsum([0, *map(len, images)]).astype(np.int64))
    sample[FRAMES] = b"".join(images)
    return sample


def evaluation_contexts(entry: EvaluationEntry, most: int) -> dict[int, tuple[int, ...]]:
    """The k-view contexts of an evaluation entry for k = 2 .. ``most`` (and the entry's own count), those
    that fit between its outer context frames."""
    counts = sorted({*range(2, most + 1), len(entry.context)})
    contexts = {k: evaluation_context(entry.context, entry.target, k) for k in counts}
    return {k: c for k, c in contexts.items() if c is not None}


def evaluation_members(scene: Scene, entry: EvaluationEntry, cfg: ConvertConfig) -> dict[str, bytes]:
    """An evaluation shard sample: the entry's context and targets, the extra frames of its k-view contexts,
    and the targets' highlight masks when the scene carries its specular magnitude. Meta first."""
    contexts = evaluation_contexts(entry, cfg.eval_context_views)
    extra = sorted({f for c in contexts.values() for f in c} - set(entry.context) - set(entry.target))
    frames = [*entry.context, *entry.target, *extra]
    meta = {
        "scene": scene.key,
        "dataset": scene.dataset,
        "context": list(entry.context),
        "target": list(entry.target),
        "gap": int(entry.context[-1] - entry.context[0]),
        "overlap": entry.overlap,
        "extra": extra,
        "context_views": {str(k): list(c) for k, c in contexts.items()},
    }
    stems = evaluation_stems(len(entry.context), len(entry.target), len(extra))
    images, ks = _frames(scene, frames, cfg)
    sample = {META: json.dumps(meta).encode()}
    sample.update((image_member(stem), image) for stem, image in zip(stems, images))
    if scene.specular is not None:
        for stem, f in zip(stems[len(entry.context) :], entry.target):
            mask = highlight_mask(scene.specular[f], cfg.size, cfg.specular_threshold)
            sample[highlight_member(stem)] = _png(mask)
    sample[EXTRINSICS] = _npy(scene.c2w[frames].astype(np.float32))
    sample[INTRINSICS] = _npy(ks.astype(np.float32))
    return sample


# ----------------------------------------------------------------------------------------------- jobs


@dataclass(frozen=True)
class _Job:
    split: str
    unit: Unit
    shard: str
    reader: Reader
    cfg: ConvertConfig
    index: dict[str, EvaluationEntry | None] | None  # evaluation splits with an index: its entries for the unit
    held_out: frozenset[str] = frozenset()  # train split: scenes kept for validation (left out here)
    only: frozenset[str] | None = None  # validation held out of train: convert these scenes of the unit only

    @property
    def evaluation(self) -> bool:
        return self.split != "train"


def _settings(job: _Job) -> dict[str, Any]:
    """What a finished shard must have been made with to be kept by a rerun."""
    index = None
    if job.index is not None:
        text = json.dumps({k: None if e is None else e.to_json() for k, e in sorted(job.index.items())})
        index = hashlib.sha256(text.encode()).hexdigest()
    keys = None
    if job.held_out or job.only is not None:
        text = json.dumps([sorted(job.held_out), None if job.only is None else sorted(job.only)])
        keys = hashlib.sha256(text.encode()).hexdigest()
    return json.loads(json.dumps({"config": asdict(job.cfg), "source_config": asdict(job.reader.cfg),
                                  "evaluation_index_sha256": index, "held_out_sha256": keys}))  # fmt: skip


def _stat(path: Path) -> list[Any]:
    st = path.stat()
    return [str(path), st.st_size, st.st_mtime_ns]


def _sources_unchanged(sources: list[list[Any]]) -> bool:
    try:
        return all(_stat(Path(path)) == [path, size, mtime] for path, size, mtime in sources)
    except OSError:
        return False


def _finished(job: _Job) -> dict[str, Any] | None:
    """The sidecar record if the unit's shard was made with the same settings from unchanged sources and still
    matches its checksum."""
    shard = Path(job.shard)
    sidecar = shard.with_suffix(".json")
    if not (shard.exists() and sidecar.exists()):
        return None
    try:
        record = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    same = isinstance(record, dict) and all(record.get(k) == v for k, v in _settings(job).items())
    if not same or not _sources_unchanged(record.get("sources", [])):
        return None
    return record if record.get("sha256") == sha256(shard) else None


def _evaluation_entry(scene: Scene, job: _Job) -> EvaluationEntry:
    """The scene's evaluation sample: its index entry, or the deterministic sample of a scene without one."""
    cfg = job.cfg
    if job.index is None:  # _check made sure the scene spans the context gap
        context, target = evaluation_sample(len(scene), cfg.context_gap, cfg.num_targets)
        return EvaluationEntry(context, target, None)
    entry = job.index.get(scene.key)
    if entry is None:
        raise SceneError("not_in_evaluation_index", f"{scene.key}: no entry in the evaluation index")
    last = max(entry.context + entry.target)
    if last >= len(scene):
        raise SceneError("evaluation_frames_out_of_range", f"{scene.key}: the evaluation index names frame "
                         f"{last}, the scene has {len(scene)} frames")  # fmt: skip
    return entry


def _check(scene: Scene, job: _Job) -> None:
    cfg = job.cfg
    need, why, reason = 3, "a sample", "too_few_frames"
    if not job.evaluation:  # gaps count the frames kept (every frame_stride-th)
        need, why = cfg.min_gap * cfg.frame_stride + 1, f"the smallest context gap ({cfg.min_gap}, --min-gap)"
        reason = "shorter_than_min_gap"
    elif job.index is None and cfg.context_gap + 1 > need:  # the deterministic evaluation sample's span
        need, why = cfg.context_gap + 1, f"a context gap of {cfg.context_gap} (--context-gap)"
    check_scene(scene, max_fov_deg=cfg.max_fov_deg, min_baseline=cfg.min_baseline,
                expect_shape=cfg.expect_shape, min_frames=need, min_frames_why=why,
                min_frames_reason=reason)  # fmt: skip


def convert_unit(job: _Job) -> dict[str, Any]:
    """Convert one unit into one shard; returns its record (also written as the shard's sidecar JSON). A unit
    that yields no sample writes no shard (and removes a stale one). An ``OSError`` (a full disk) leaves no
    temporary file and names the shard."""
    shard, cfg = Path(job.shard), job.cfg
    skips: Counter[str] = Counter()
    refused: dict[str, list[str]] = {}  # scene key -> [reason, message]
    seen, keys, frames, stated, sources = 0, [], {}, {}, {}
    taken: dict[str, str] = {}  # shard key -> the scene key that has it
    highlight = masked = 0
    try:
        with ShardWriter(shard) as writer:
            for item in job.reader.scenes(job.unit):
                if item.key in job.held_out or (job.only is not None and item.key not in job.only):
                    continue  # another split's scene (held-out scenes go to validation)
                if isinstance(item, Skipped):
                    seen += bool(item.key)
                    skips[item.reason] += 1
                    refused[item.key or job.unit.path.name] = [item.reason, item.message]
                    continue
                seen += 1
                if not item.key:
                    skips["bad_key"] += 1
                    where = f"#{seen} of {job.unit.path.name}"
                    refused[where] = ["bad_key", f"scene {where} has no key: give it one"]
                    continue
                shard_key = safe_key(item.key)
                other = taken.get(shard_key)
                if other is not None:  # one shard key, one sample: a second would be read into the first
                    skips["duplicate_key"] += 1
                    refused[f"{item.key} (again)" if other == item.key else item.key] = [
                        "duplicate_key", f"{item.key!r}: its shard key {shard_key!r} is taken by {other!r} in "
                        "the same source file; give each scene a key of its own"]  # fmt: skip
                    continue
                taken[shard_key] = item.key
                try:
                    _check(item, job)
                    if job.evaluation:
                        entry = _evaluation_entry(item, job)
                        sample = evaluation_members(item, entry, cfg)
                        stated[item.key] = {**entry.to_json(), "context_views": json.loads(sample[META])
                                            ["context_views"]}  # fmt: skip
                        if item.names is not None:
                            used = [*entry.context, *entry.target]
                            stated[item.key]["files"] = [item.names[f] for f in used]
                    else:
                        sample = scene_sample(item, cfg)
                        frames[item.key] = len(range(0, len(item), cfg.frame_stride))
                except SceneError as err:
                    skips[err.reason] += 1
                    refused[item.key] = [err.reason, str(err)]
                    continue
                except (OSError, MemoryError):
                    raise
                except Exception as err:  # noqa: BLE001 - a frame that does not decode skips its scene, never the run
                    skips["corrupt_image"] += 1
                    refused[item.key] = ["corrupt_image", f"{item.key}: a frame cannot be decoded ({err})"]
                    continue
                for name, data in sample.items():
                    if name.endswith(highlight_member("")):
                        with Image.open(io.BytesIO(data)) as im:
                            mask = np.asarray(im) > 0
                        highlight, masked = highlight + int(mask.sum()), masked + mask.size
                writer.add(shard_key, sample)
                keys.append(item.key)
                sources.update((str(p), None) for p in item.sources)
            if writer.samples:
                writer.commit()
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(shard)) from None
    record: dict[str, Any] = {
        "shard": shard.name if keys else None,  # no sample, no shard (and no sidecar: a rerun retries it)
        "split": job.split,
        "source": job.unit.path.name,
        "samples": len(keys),
        "scenes": len(keys),
        "scenes_seen": seen,
        "scene_keys": keys,
        "scene_frames": frames,
        "skips": dict(sorted(skips.items())),
        "refused": refused,
        "evaluation_samples": stated,
        "highlight_pixels": highlight,
        "masked_target_pixels": masked,
        "sha256": None,
        "bytes": 0,
        "sources": [_stat(Path(p)) for p in sources],
        **_settings(job),
    }
    if not keys:
        shard.unlink(missing_ok=True)  # a shard of an earlier conversion of this unit is stale now
        shard.with_suffix(".json").unlink(missing_ok=True)
        return record
    record.update(sha256=sha256(shard), bytes=shard.stat().st_size)
    atomic_write(shard.with_suffix(".json"), lambda f: f.write(json.dumps(record, indent=1).encode()))
    return record


def report_skips(record: dict[str, Any]) -> None:
    """Name on stderr what a unit's conversion left out, one line each: the reason code and the message."""
    where = f"{record['split']}/{record['source']}"
    for reason, message in record.get("refused", {}).values():
        print(f"to_shards: {where}: skipped ({reason}): {message}", file=sys.stderr)
    if not record.get("refused") and not record["samples"]:
        print(f"to_shards: {where}: no sample, no shard written", file=sys.stderr)


# ----------------------------------------------------------------------------------------------- conversion


def held_out_keys(keys: list[str], count: int, seed: int) -> list[str]:
    """The ``count`` training scenes held out for validation: the keys ranked by a hash of the conversion
    seed and the key, so the choice depends on neither the unit order nor the number of workers. Sorted."""
    if not 0 <= count < len(keys):
        raise UserError(
            f"--val-scenes {count}: need 0 <= N < the {len(keys)} training scenes (leave some to train on)"
        )
    rank = sorted(keys, key=lambda k: hashlib.sha256(f"{seed}/validation/{k}".encode()).hexdigest())
    return sorted(rank[:count])


SOURCE_OPTIONS = {f.name for f in fields(SourceConfig)} - {"fmt"}
SHARD_FIELDS = ("shard", "source", "samples", "scenes", "sha256", "bytes", "scene_frames")  # a manifest's shard


def convert_dataset(
    src: str | Path,
    out: str | Path,
    fmt: str = "chunks",
    *,
    eval_index: str | Path | None = None,
    val_index: str | Path | None = None,
    val_scenes: int = 0,
    workers: int = 1,
    progress: bool = True,
    **options: Any,
) -> dict[str, Any]:
    """Convert a source in ``fmt`` (a key of :data:`aesplat.data.sources.READERS`) into
    ``out/<split>/*.tar`` and ``out/manifest.json``; returns the manifest.

    options: :class:`SourceConfig`'s (``dataset``, and for folder formats ``split``, ``capture_path``,
    ``images``, ``frame_order``) and :class:`ConvertConfig`'s. ``min_gap`` defaults to the source's
    ``dataset.json`` gap range, else 25; ``context_gap`` to ``min_gap``.
    eval_index: the evaluation index JSON of the test split (default ``src/evaluation_index.json`` if it
    exists); val_index: the same for a validation split of the source (default ``src/validation_index.json``).
    val_scenes: hold this many training scenes out as the validation split (sources without one: RealEstate10K,
    ACID; deterministic from their keys and ``seed``); the manifest lists them.
    """
    src, out = Path(src), Path(out)
    unknown = set(options) - SOURCE_OPTIONS - {f.name for f in fields(ConvertConfig)}
    if unknown:
        raise TypeError(f"convert_dataset() got unknown options {sorted(unknown)}")
    source = SourceConfig(fmt=fmt, **{k: v for k, v in options.items() if k in SOURCE_OPTIONS})
    reader = make_reader(src, source)
    info = reader.info()
    writer_options = {k: v for k, v in options.items() if k not in SOURCE_OPTIONS and v is not None}
    gaps = info.get("gap_range", [ConvertConfig.min_gap])
    writer_options.setdefault("min_gap", int(gaps[0]))
    writer_options.setdefault("context_gap", writer_options["min_gap"])
    if writer_options.get("expect_shape") is not None:
        writer_options["expect_shape"] = tuple(writer_options["expect_shape"])
    cfg = ConvertConfig(**writer_options)
    units = reader.units()
    unit_keys: dict[Unit, list[str]] = {}

    def keys_of(unit: Unit) -> list[str]:
        if unit not in unit_keys:
            unit_keys[unit] = reader.keys(unit)
        return unit_keys[unit]

    splits = sorted({u.split for u in units}, key=("train", "validation", "test").index)
    if val_scenes < 0:
        raise UserError(f"--val-scenes must be >= 0, got {val_scenes}")
    held: list[str] = []
    if val_scenes:
        if "validation" in splits:
            raise UserError(f"{src} already has a validation/ split; drop --val-scenes (it holds out training "
                            "scenes only for sources without one)")  # fmt: skip
        if "train" not in splits:
            raise UserError(
                f"--val-scenes holds out training scenes, but {src} has none (captures: --split train)"
            )
        keys = [key for u in units if u.split == "train" for key in keys_of(u)]
        held = held_out_keys(sorted(set(keys)), val_scenes, cfg.seed)
        splits.insert(1, "validation")
    if eval_index is None and "test" in splits and (src / "evaluation_index.json").is_file():
        eval_index = src / "evaluation_index.json"
    if eval_index is not None and "test" not in splits:
        raise UserError(
            "--eval-index picks test samples; this source has no test split (captures: --split test)"
        )
    if val_index is None and "validation" in splits and not held and (src / "validation_index.json").is_file():
        val_index = src / "validation_index.json"
    indexes = {"train": None, "validation": None if val_index is None else read_evaluation_index(val_index),
               "test": None if eval_index is None else read_evaluation_index(eval_index)}  # fmt: skip

    for leftover in out.glob("*/*.tmp"):  # what a killed conversion left behind
        leftover.unlink(missing_ok=True)
    for folder in [out, *(d for d in out.glob("*") if d.is_dir())]:
        remove_partials(folder)
    jobs, records = [], []
    held_set = frozenset(held)
    for split in splits:
        (out / split).mkdir(parents=True, exist_ok=True)
        from_train = split == "validation" and bool(held)
        for unit in units:
            if unit.split != ("train" if from_train else split):
                continue
            keys_of_unit = set(keys_of(unit)) if (from_train or indexes[split] is not None) else None
            if from_train and not keys_of_unit & held_set:
                continue
            index = indexes[split]
            if index is not None:  # the unit's entries only: a change elsewhere in the index keeps this shard
                index = {k: e for k, e in index.items() if k in keys_of_unit}
            job = _Job(split, unit, str(out / split / f"{split}-{unit.name}.tar"), reader, cfg, index,
                       held_out=held_set if split == "train" else frozenset(),
                       only=held_set if from_train else None)  # fmt: skip
            done = _finished(job)
            if done is not None:
                records.append(done)
            else:
                jobs.append(job)

    from tqdm import tqdm

    try:
        with tqdm(total=len(jobs), desc="shards", disable=not progress) as bar:
            for record in _run(jobs, workers):
                records.append(record)
                report_skips(record)
                bar.update()
    except OSError as err:
        raise UserError(
            f"cannot write {err.filename or out}: {err.strerror or err}; free space (or fix the "
            "permission) and rerun the same command: finished shards are kept"
        ) from None
    refuse_repeated_keys(records)
    manifest = _manifest(src, reader, cfg, splits, records, indexes, held, eval_index, val_index)
    try:
        atomic_write(out / "manifest.json", lambda f: f.write(json.dumps(manifest, indent=1).encode()))
    except OSError as err:
        raise UserError(
            f"cannot write {out / 'manifest.json'}: {err.strerror or err}; free space and rerun the "
            "same command: finished shards are kept"
        ) from None
    return manifest


def refuse_repeated_keys(records: list[dict[str, Any]]) -> None:
    """One line when one scene key is in two shards of a split: evaluation results, the manifest and the
    validation hold-out name a scene by its key, so a key must name one scene."""
    where: dict[tuple[str, str], str] = {}
    for record in sorted(records, key=lambda r: r["source"]):
        for key in record["scene_keys"]:
            first = where.setdefault((record["split"], key), record["source"])
            if first != record["source"]:
                raise UserError(
                    f"scene key {key!r} is in two source files of the {record['split']} split ({first} and "
                    f"{record['source']}): give each scene a key of its own and convert again (finished "
                    "shards are kept)"
                )


def _run(jobs: list[_Job], workers: int) -> Iterator[dict[str, Any]]:
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            yield from pool.map(convert_unit, jobs)
    else:
        yield from map(convert_unit, jobs)


def _manifest(
    src: Path,
    reader: Reader,
    cfg: ConvertConfig,
    splits: list[str],
    records: list[dict[str, Any]],
    indexes: dict[str, Any],
    held: list[str],
    eval_index: Any,
    val_index: Any,
) -> dict[str, Any]:
    manifest: dict[str, Any] = {
        "version": MANIFEST_VERSION,
        "source": str(src),
        "format": reader.cfg.fmt,
        "config": asdict(cfg),
        "source_config": asdict(reader.cfg),
        "evaluation_index": None if eval_index is None else str(eval_index),
        "validation_index": None if val_index is None else str(val_index),
        "splits": {},
    }
    for split in splits:
        recs = sorted((r for r in records if r["split"] == split), key=lambda r: r["source"])
        skips: Counter[str] = Counter()
        for r in recs:
            skips.update(r["skips"])
        made = [r for r in recs if r["shard"] is not None]
        entry: dict[str, Any] = {
            "layout": "samples" if split != "train" else "scenes",
            "samples": sum(r["samples"] for r in recs),
            "scenes": sum(r["scenes"] for r in recs),
            "scenes_seen": sum(r["scenes_seen"] for r in recs),
            "skips": dict(sorted(skips.items())),
            "refused": {k: message for r in recs for k, (_, message) in r["refused"].items()},
            "shards": [{k: r[k] for k in SHARD_FIELDS} for r in made],
        }
        if split == "train":
            entry["frames"] = sum(sum(r["scene_frames"].values()) for r in made)
        else:
            entry["context_views"] = cfg.eval_context_views
            entry["evaluation_samples"] = {k: v for r in made for k, v in r["evaluation_samples"].items()}
        masked = sum(r.get("masked_target_pixels", 0) for r in recs)
        if masked:  # share of target pixels marked as highlights (tgtI.spec.png), at the output size
            entry["highlight_share"] = sum(r.get("highlight_pixels", 0) for r in recs) / masked
        if indexes[split] is not None:
            wanted = {k for k, v in indexes[split].items() if v is not None}
            found = {k for r in made for k in r["scene_keys"]}
            entry["evaluation_index_entries"] = len(wanted)
            entry["evaluation_index_missing"] = len(wanted - found)
        if split == "validation" and held:  # which training scenes became the validation split, and how
            entry["held_out_from_train"] = {"count": len(held), "seed": cfg.seed, "scene_keys": held}
        manifest["splits"][split] = entry
    return manifest
