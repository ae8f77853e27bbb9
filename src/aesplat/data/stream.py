"""Streaming shards into ``BatchedExample`` batches, split explicitly by rank and worker (docs/data.md).

- Training reads whole scenes (layout ``scenes``) and draws every example at run time
  (:mod:`aesplat.data.sampler`): the context gap from the curriculum's range at the step the batch is trained
  at, a random start, extra context views and targets between the outer two; or, with ``fixed_pool``, one of a
  pool of examples drawn once per scene. Every (rank, worker) resamples its scenes forever through a shuffle
  buffer and yields exactly its share of ``batches_per_rank`` batches, so every rank sees the same number of
  batches (no DDP hang); ranks read disjoint scenes. Epochs are blocks of ``batches_per_rank`` global steps.
  Batch j of the epoch that starts at step e is drawn for step e + j (its curriculum range and its count of
  context views), and the random streams are seeded with (seed, rank, worker role, e). So the data depend
  only on those, not on timing or prefetching, and an iterator started in the middle of an epoch (a run
  resumed from a mid-epoch checkpoint) replays the epoch's first batches without yielding them and continues
  exactly where the interrupted run stopped.
- Evaluation reads deterministic samples (layout ``samples``) in a fixed order, every sample exactly once
  across all ranks and workers, with the k-view context the shards state for the evaluated count.
- A corrupt sample or shard, a scene too short for the current range, are skipped, counted in a shared counter
  table and logged (the scene named), never fatal.

Workers batch samples themselves (the DataLoader runs with ``batch_size=None``) so batch counts are exact.
"""

from __future__ import annotations

import io
import json
import logging
import os
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from aesplat.types import BatchedExample, BatchedViews

from .curriculum import GapCurriculum
from .manifest import SceneRef
from .sampler import ContextCount, ViewPick, fixed_pool, gap_range, sample_views, scene_seed, smallest_gap
from .sources.base import safe_key

log = logging.getLogger("aesplat.data")

COUNTERS = ("corrupt_samples", "corrupt_shards", "curriculum_skipped", "too_few_targets", "scene_too_short",
            "too_few_between", "no_context_views")  # fmt: skip
REFLECT = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
POOL_TARGETS = 3  # targets stored per fixed-pool example, as the pre-drawn samples of earlier shards held


def new_counters(num_workers: int) -> Tensor:
    """Shared-memory counter table [workers + 1, len(COUNTERS)]: one row per worker (row 0 = main process),
    so workers never write the same cell."""
    return torch.zeros(num_workers + 1, len(COUNTERS), dtype=torch.int64).share_memory_()


def read_tar(path: str | Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """Stream the samples of a WebDataset tar: (key, {extension: bytes}), members grouped by key.

    Raises ``tarfile.ReadError`` / ``EOFError`` / ``OSError`` on a truncated or corrupt tar (the incomplete
    sample at the point of failure is never yielded, wherever the file was cut).
    """
    key, sample = None, {}
    size = os.path.getsize(path)
    with tarfile.open(path, "r|") as tar:
        for member in tar:
            if not member.isfile():
                continue
            name = member.name.rsplit("/", 1)[-1]
            k, _, ext = name.partition(".")
            f = tar.extractfile(member)
            data = f.read() if f is not None else b""
            if len(data) != member.size:
                raise tarfile.ReadError(f"member {member.name} truncated")
            if k != key:
                if key is not None:
                    yield key, sample
                key, sample = k, {}
            sample[ext] = data
        # tarfile ends quietly when the file stops inside a header: a whole archive ends with two zero blocks.
        if size - tar.offset < 2 * tarfile.BLOCKSIZE:
            raise tarfile.ReadError(f"archive truncated after {tar.offset} bytes (no end-of-archive marker)")
    if key is not None:
        yield key, sample


@dataclass(frozen=True)
class SceneEntry:
    """A whole-scene sample as indexed, not read: its small members' bytes (meta, cameras, frame offsets) and
    where its frames' JPEGs lie in the shard (byte offset and length of ``frames.jpgs``)."""

    shard: str
    key: str
    members: dict[str, bytes]
    frames_at: int
    frames_size: int

    @property
    def num_frames(self) -> int:
        return len(json.loads(self.members["meta.json"])["frames"])


def index_scenes(path: str | Path) -> Iterator[SceneEntry]:
    """The whole-scene samples of a training shard, reading only the headers and the small members: the frames
    stay on disk until an example picks some (:class:`FrameReader`). Raises ``tarfile.ReadError`` / ``OSError``
    on a truncated or corrupt shard (the incomplete scene at the point of failure is never yielded)."""
    size = os.path.getsize(path)
    key, members, span = None, {}, None
    with tarfile.open(path, "r:") as tar:  # random access: headers are read, frame bytes are skipped
        for member in tar:
            if not member.isfile():
                continue
            k, _, ext = member.name.rsplit("/", 1)[-1].partition(".")
            if member.offset_data + member.size > size:
                raise tarfile.ReadError(f"member {member.name} truncated")
            if k != key:
                if key is not None and span is not None:
                    yield SceneEntry(str(path), key, members, *span)
                key, members, span = k, {}, None
            if ext == "frames.jpgs":
                span = (member.offset_data, member.size)
            else:
                members[ext] = tar.extractfile(member).read()
        if size - tar.offset < 2 * tarfile.BLOCKSIZE:  # see read_tar: a whole archive ends with two zero blocks
            raise tarfile.ReadError(f"archive truncated after {tar.offset} bytes (no end-of-archive marker)")
    if key is not None and span is not None:
        yield SceneEntry(str(path), key, members, *span)


class FrameReader:
    """Reads a scene's picked frames from its shard, keeping the last few shards open (one reader per worker:
    it is made empty in each process)."""

    def __init__(self, keep: int = 8) -> None:
        self.keep = keep
        self._open: dict[str, Any] = {}

    def frames(self, entry: SceneEntry, picks: list[int]) -> list[bytes]:
        offsets = np.load(io.BytesIO(entry.members["frames.offsets.npy"]))
        if offsets[-1] != entry.frames_size or (np.diff(offsets) <= 0).any():
            raise ValueError(
                f"frame offsets {offsets[:3]}… do not describe {entry.frames_size} bytes of frames"
            )
        f = self._open.pop(entry.shard, None) or open(entry.shard, "rb")  # noqa: SIM115 - kept open, closed below
        self._open[entry.shard] = f  # most recently used last
        while len(self._open) > self.keep:
            self._open.pop(next(iter(self._open))).close()
        out = []
        for v in picks:
            f.seek(entry.frames_at + int(offsets[v]))
            data = f.read(int(offsets[v + 1] - offsets[v]))
            if len(data) != offsets[v + 1] - offsets[v]:
                raise ValueError(f"frame {v} is cut short in {entry.shard}")
            out.append(data)
        return out


def flip_views(images: Tensor, extrinsics: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Mirror views horizontally and the world with them: images [..., 3, H, W], camera-to-world [..., 4, 4],
    normalised intrinsics [..., 3, 3]. Pixel u maps to W - u; a world point X maps to diag(-1, 1, 1) X."""
    intrinsics = intrinsics.clone()
    intrinsics[..., 0, 2] = 1.0 - intrinsics[..., 0, 2]
    reflect = REFLECT.to(extrinsics)
    return images.flip(-1), reflect @ extrinsics @ reflect, intrinsics


@dataclass(frozen=True)
class StreamConfig:
    """What a stream needs to turn shard samples into batches (built by the DataModule).

    context_views: the count of context views (training: per batch, see :class:`ContextCount`; evaluation: a
    fixed count); num_target_views: targets per example (None: every target of an evaluation sample);
    min_target_distance: frames between a target and the outer context frames, at least; examples_per_scene:
    training examples drawn from each scene read (they enter the shuffle buffer separately); fixed_pool: 0
    draws every example afresh, N > 0 draws N examples per scene once (seeded) and reuses them."""

    image_size: int
    batch_size: int
    context_views: ContextCount = ContextCount(2, 2)
    num_target_views: int | None = 1
    flip_augment: bool = False
    min_target_distance: int = 1
    examples_per_scene: int = 1
    fixed_pool: int = 0
    large_scale: int = 1  # evaluation: also decode each target at image_size x this (1: no)


@dataclass
class Example:
    """One decoded example (context views first, then targets).

    images uint8 [V, 3, H, W]; extrinsics [V, 4, 4] camera-to-world; intrinsics [V, 3, 3] normalised;
    index int64 [V] source frame ids; gap: context gap in stored frames (what the curriculum judges);
    overlap: NaN where unknown; highlight bool [Vt, 1, H, W] target highlight masks, or None; target_large
    uint8 [Vt, 3, sH, sW] the targets at ``StreamConfig.large_scale`` times the size, or None."""

    images: Tensor
    extrinsics: Tensor
    intrinsics: Tensor
    index: Tensor
    num_context: int
    scene: str
    dataset: str
    gap: int
    overlap: float = float("nan")
    highlight: Tensor | None = None
    target_large: Tensor | None = None


def _image(data: bytes, name: str, size: int) -> Tensor:
    """An encoded square image -> uint8 [3, size, size] (resized when stored at another size: square to square
    maps the full extent onto the full extent, so normalised intrinsics are unchanged)."""
    with Image.open(io.BytesIO(data)) as pil:
        img = torch.from_numpy(np.array(pil.convert("RGB"))).permute(2, 0, 1)
    if img.shape[1:] != (size, size):
        if img.shape[1] != img.shape[2]:
            raise ValueError(f"{name} is {tuple(img.shape[1:])}, shard images must be square")
        img = F.interpolate(img[None].float(), size=(size, size), mode="bilinear", antialias=True,
                            align_corners=False)[0].round().clamp(0, 255).to(torch.uint8)  # fmt: skip
    return img


def _mask(data: bytes, name: str, size: int) -> Tensor:
    """A highlight mask PNG -> bool [1, size, size] (nearest neighbour keeps it a mask)."""
    with Image.open(io.BytesIO(data)) as pil:
        mask = torch.from_numpy(np.array(pil.convert("L")) > 127)[None]
    if mask.shape[-1] != mask.shape[-2]:
        raise ValueError(f"{name} is {tuple(mask.shape[1:])}, shard masks must be square")
    if mask.shape[-1] != size:
        mask = F.interpolate(mask[None].float(), size=(size, size), mode="nearest-exact")[0] > 0.5
    return mask


def _cameras(raw: dict[str, bytes], rows: int) -> tuple[Tensor, Tensor]:
    extrinsics = torch.from_numpy(np.load(io.BytesIO(raw["extrinsics.npy"]))).float()
    intrinsics = torch.from_numpy(np.load(io.BytesIO(raw["intrinsics.npy"]))).float()
    if extrinsics.shape != (rows, 4, 4) or intrinsics.shape != (rows, 3, 3):
        raise ValueError(f"camera arrays {tuple(extrinsics.shape)}, {tuple(intrinsics.shape)} do not match "
                         f"{rows} frames")  # fmt: skip
    if not (torch.isfinite(extrinsics).all() and torch.isfinite(intrinsics).all()):
        raise ValueError("non-finite cameras")
    return extrinsics, intrinsics


def _flip(example: Example, cfg: StreamConfig, rng: np.random.Generator) -> Example:
    if cfg.flip_augment and rng.uniform() < 0.5:
        example.images, example.extrinsics, example.intrinsics = flip_views(
            example.images, example.extrinsics, example.intrinsics
        )
    return example


def decode_scene_example(entry: SceneEntry, reader: FrameReader, pick: ViewPick, cfg: StreamConfig,
                         rng: np.random.Generator) -> Example:  # fmt: skip
    """A training example from a whole-scene sample: only the picked frames are read and decoded. ``rng`` draws
    the flip. ``ValueError`` on a bad sample."""
    meta = json.loads(entry.members["meta.json"])
    frames = list(meta["frames"])
    views = [*pick.context, *pick.target]
    extrinsics, intrinsics = _cameras(entry.members, len(frames))
    data = reader.frames(entry, views)
    images = torch.stack([_image(d, f"frame {v}", cfg.image_size) for v, d in zip(views, data)])
    example = Example(
        images,
        extrinsics[views],
        intrinsics[views],
        torch.tensor([frames[v] for v in views]),
        len(pick.context),
        str(meta["scene"]),
        str(meta.get("dataset", "")),
        pick.gap,
    )
    return _flip(example, cfg, rng)


class NoContext(ValueError):
    """An evaluation sample that carries no context of the evaluated count (shards made for fewer views)."""


class TooFewTargets(ValueError):
    """An evaluation sample with fewer targets than ``data.eval_num_target_views`` asks for."""


def decode_evaluation_sample(raw: dict[str, bytes], cfg: StreamConfig) -> Example:
    """An evaluation example: the sample's context of ``cfg.context_views`` views (its index's own, or the
    k-view context the shards state), every target or the first ``num_target_views``. ``NoContext`` when the
    sample has no context of that count; ``ValueError`` on a bad sample."""
    meta = json.loads(raw["meta.json"])
    context, target, extra = list(meta["context"]), list(meta["target"]), list(meta.get("extra", []))
    names = {f: f"ctx{i}" for i, f in enumerate(context)}
    names.update({f: f"tgt{i}" for i, f in enumerate(target)})
    names.update({f: f"xtr{i}" for i, f in enumerate(extra)})
    rows = {f: i for i, f in enumerate([*context, *target, *extra])}
    k = cfg.context_views.lo
    chosen = meta.get("context_views", {}).get(str(k)) or (context if len(context) == k else None)
    if chosen is None:
        raise NoContext(f"it carries no {k}-view context (too few frames between its outer context views, or "
                        f"converted with --eval-context-views below {k})")  # fmt: skip
    want = len(target) if cfg.num_target_views is None else cfg.num_target_views
    if len(target) < want:
        raise TooFewTargets(f"it has {len(target)} targets, data.eval_num_target_views asks for {want}")
    targets = target[:want]
    views = [*chosen, *targets]
    extrinsics, intrinsics = _cameras(raw, len(rows))
    picked = [rows[f] for f in views]
    images = torch.stack([_image(raw[f"{names[f]}.jpg"], names[f], cfg.image_size) for f in views])
    masks = [f"{names[f]}.spec.png" for f in targets]
    highlight = None
    if masks and all(m in raw for m in masks):
        highlight = torch.stack([_mask(raw[m], m, cfg.image_size) for m in masks])
    large = None
    if cfg.large_scale > 1:
        size = cfg.image_size * cfg.large_scale
        large = torch.stack([_image(raw[f"{names[f]}.jpg"], names[f], size) for f in targets])
    overlap = meta.get("overlap")
    return Example(images, extrinsics[picked], intrinsics[picked], torch.tensor(views, dtype=torch.int64),
                   len(chosen), str(meta["scene"]), str(meta.get("dataset", "")), int(meta["gap"]),
                   float("nan") if overlap is None else float(overlap), highlight, large)  # fmt: skip


def collate(examples: list[Example]) -> BatchedExample:
    """Decoded examples -> ``BatchedExample`` with uint8 images [B, V, 3, H, W]."""
    counts = sorted({(e.num_context, e.images.shape[0] - e.num_context) for e in examples})
    if len(counts) > 1:
        raise ValueError(
            f"examples of one batch have different numbers of (context, target) views {counts} (scenes "
            f"{[e.scene for e in examples]}): set eval_num_target_views or eval_batch_size=1"
        )
    nc = counts[0][0]

    def views(sl: slice) -> BatchedViews:
        return BatchedViews(
            images=torch.stack([e.images[sl] for e in examples]),
            extrinsics=torch.stack([e.extrinsics[sl] for e in examples]),
            intrinsics=torch.stack([e.intrinsics[sl] for e in examples]),
            index=torch.stack([e.index[sl] for e in examples]),
        )

    with_masks = [e.highlight is not None for e in examples]
    if any(with_masks) and not all(with_masks):
        raise ValueError(
            f"only some samples of one batch have highlight masks (scenes {[e.scene for e in examples]}): "
            "evaluate shards with and without masks separately, or set eval_batch_size=1"
        )
    return BatchedExample(
        context=views(slice(0, nc)),
        target=views(slice(nc, None)),
        scene=[e.scene for e in examples],
        overlap=torch.tensor([e.overlap for e in examples], dtype=torch.float32),
        gap=torch.tensor([e.gap for e in examples], dtype=torch.int64),
        dataset=[e.dataset for e in examples],
        highlight=torch.stack([e.highlight for e in examples]) if all(with_masks) else None,
        target_large=None
        if examples[0].target_large is None
        else torch.stack([e.target_large for e in examples]),
    )


def _worker() -> tuple[int, int]:
    info = get_worker_info()
    return (0, 1) if info is None else (info.id, info.num_workers)


def partition(scenes: list[SceneRef], part: int, parts: int) -> list[SceneRef]:
    """Part ``part`` of ``parts`` disjoint parts of ``scenes`` (sorted by shard): whole shards dealt out when
    there are at least as many shards as parts (each shard read by one part only), else scenes dealt out."""
    shards = sorted({s.shard for s in scenes})
    if len(shards) >= parts:
        mine = set(shards[part::parts])
        return [s for s in scenes if s.shard in mine]
    return scenes[part::parts]


class _ShardStream(IterableDataset):
    """Shared plumbing: rank, counters and safe reading."""

    def __init__(self, cfg: StreamConfig, rank: int, world_size: int, counters: Tensor) -> None:
        super().__init__()
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is outside world size {world_size}")
        self.cfg = cfg
        self.rank = rank
        self.world_size = world_size
        self.counters = counters

    def _count(self, what: str, n: int = 1) -> None:
        info = get_worker_info()
        row = 0 if info is None else min(info.id + 1, self.counters.shape[0] - 1)  # one row per process
        self.counters[row, COUNTERS.index(what)] += n

    def _samples(self, shard: str, scenes: bool = False) -> Iterator:
        """The samples of a shard (``scenes``: indexed :class:`SceneEntry` objects); a corrupt shard is
        abandoned at the point of damage, counted and logged."""
        try:
            yield from index_scenes(shard) if scenes else read_tar(shard)
        except (tarfile.TarError, EOFError, OSError, ValueError) as e:
            self._count("corrupt_shards")
            log.warning("skipping the rest of corrupt shard %s: %s (counted in corrupt_shards)", shard, e)


class TrainStream(_ShardStream):
    """Infinite training stream over whole scenes, cut to ``batches_per_rank`` batches per rank (per epoch).

    scenes: every training scene (:func:`aesplat.data.manifest.training_scenes`); this rank reads its part
    (:func:`partition`). step: shared int64 [1] tensor holding the global step; read when an epoch's iterator
    starts. Epochs are blocks of ``batches_per_rank`` steps, so a step inside a block means "resume this epoch
    here".
    """

    def __init__(self, scenes: list[SceneRef], cfg: StreamConfig, rank: int, world_size: int, counters: Tensor,
                 step: Tensor, curriculum: GapCurriculum, batches_per_rank: int, seed: int = 0,
                 shuffle_buffer: int = 64) -> None:  # fmt: skip
        super().__init__(cfg, rank, world_size, counters)
        if batches_per_rank < 1:
            raise ValueError(f"train_batches_per_epoch must be >= 1, got {batches_per_rank}")
        self.scenes = partition(sorted(scenes, key=lambda s: (s.shard, s.key)), rank, world_size)
        if not self.scenes:
            raise ValueError(
                f"{len(scenes)} training scenes cannot give each of {world_size} ranks a scene of its own"
            )
        self.step = step
        self.curriculum = curriculum
        self.batches_per_rank = batches_per_rank
        self.seed = seed
        self.shuffle_buffer = max(1, shuffle_buffer)

    def __len__(self) -> int:
        return self.batches_per_rank

    def worker_scenes(self, role: int, num_workers: int) -> list[SceneRef]:
        """This rank's scenes for one worker role; with fewer scenes than workers every worker reads them all
        (their random streams differ, which is harmless for training)."""
        return partition(self.scenes, role, num_workers) or self.scenes

    def _raw_forever(self, scenes: list[SceneRef], rng: np.random.Generator) -> Iterator[SceneEntry | None]:
        """Indexed scenes shuffled forever, each scene read entering the buffer ``examples_per_scene`` times;
        ``None`` marks the end of each pass over the scenes."""
        keys = {safe_key(s.key) for s in scenes}
        shards = sorted({s.shard for s in scenes})
        buffer: list[SceneEntry] = []
        while True:
            read = 0
            for shard in rng.permutation(shards).tolist():
                for entry in self._samples(shard, scenes=True):
                    if entry.key not in keys:
                        continue  # another rank's or worker's scene
                    buffer.extend([entry] * self.cfg.examples_per_scene)
                    read += self.cfg.examples_per_scene
                    while len(buffer) >= self.shuffle_buffer:
                        yield buffer.pop(int(rng.integers(len(buffer))))
            if read == 0 and not buffer:
                raise RuntimeError(f"training shards {shards} hold no readable scene")
            # Keep at most half a buffer, and never more than half a pass: with fewer scenes than the buffer
            # holds, every pass still yields (else a tiny data set would look barren to the caller).
            while len(buffer) > min(self.shuffle_buffer, read) // 2:
                yield buffer.pop(int(rng.integers(len(buffer))))
            yield None

    def __iter__(self) -> Iterator[BatchedExample]:
        wid, nw = _worker()
        step = int(self.step[0])
        done = step % self.batches_per_rank  # batches of this epoch already trained on (resume)
        start = step - done
        # Batch j of the epoch comes from stream j % nw. The DataLoader asks worker 0 first, so when `done`
        # batches are already consumed, worker w plays stream (w + done) % nw: the next batch it is asked for is
        # then the next one of the epoch.
        role = (wid + done) % nw
        rng = np.random.default_rng([self.seed, self.rank, role, start])
        raw_stream = self._raw_forever(self.worker_scenes(role, nw), rng)
        draws = _Draws(reader=FrameReader())
        for j in range(role, self.batches_per_rank, nw):  # this stream's batches of the epoch
            at = start + j  # the global step batch j is trained at
            count = self.cfg.context_views.at(self.seed, at)
            batch = [self._next_example(raw_stream, rng, at, count, draws) for _ in range(self.cfg.batch_size)]
            if j >= done:  # earlier batches are replayed (their examples drew from rng) but not yielded
                yield collate(batch)

    def _pick(self, key: str, frames: int, at: int, count: int, rng: np.random.Generator) -> ViewPick | str:
        """The views of one example of a scene of ``frames`` frames at step ``at``, or the counter that says
        why the scene gives none now."""
        cfg, allowed = self.cfg, self.curriculum.allowed(at)
        vt, distance = cfg.num_target_views or 1, cfg.min_target_distance
        if cfg.fixed_pool:
            pool = fixed_pool(frames, self.curriculum.span(), cfg.fixed_pool, count, POOL_TARGETS, distance,
                              scene_seed(self.seed, key))  # fmt: skip
            if not pool:
                return "scene_too_short"
            options = [p for p in pool if allowed[0] <= p.gap <= allowed[1]]
            if not options:
                return "curriculum_skipped"
            chosen = options[int(rng.integers(len(options)))]
            if len(chosen.target) < vt:
                return "too_few_targets"
            targets = rng.choice(np.array(chosen.target), size=vt, replace=False)
            return ViewPick(chosen.context, tuple(sorted(int(t) for t in targets)))
        pick = sample_views(frames, allowed, count, vt, distance, rng)
        if pick is not None:
            return pick
        return "scene_too_short" if frames - 1 < allowed[0] else "too_few_between"

    def _next_example(self, raw_stream: Iterator, rng: np.random.Generator, at: int, count: int,
                      draws: _Draws) -> Example:  # fmt: skip
        """The next example the scenes give at step ``at`` with ``count`` context views that decodes."""
        while True:
            item = next(raw_stream)
            if item is None:  # end of a pass: two in a row without one usable example cannot recover
                draws.barren_passes = 0 if draws.accepted else draws.barren_passes + 1
                draws.accepted = 0
                if draws.barren_passes >= 2:
                    raise RuntimeError(
                        f"no training scene of this worker gives an example that decodes at step {at}: "
                        f"context gap in {self.curriculum.allowed(at)}, {count} context and "
                        f"{self.cfg.num_target_views} target views (longest scenes seen: "
                        f"{sorted(draws.lengths)[-5:]}); lower data.gap_* or the view counts, or convert "
                        "longer scenes"
                    )
                continue
            shard, key = item.shard, item.key
            try:
                frames = item.num_frames
            except Exception as e:  # noqa: BLE001 - one bad sample must never stop a multi-day run
                self._count("corrupt_samples")
                log.warning("skipping corrupt sample %s in %s: %s (counted in corrupt_samples)", key, shard, e)
                continue
            draws.lengths.add(frames)
            pick = self._pick(key, frames, at, count, rng)
            if isinstance(pick, str):
                self._count(pick)
                if pick != "curriculum_skipped" and (key, pick) not in draws.named:
                    draws.named.add((key, pick))
                    log.warning(
                        "skipping scene %s (%d frames) at step %d: no example with a context gap in %s, "
                        "%d context and %s target views (counted in %s)",
                        key,
                        frames,
                        at,
                        self.curriculum.allowed(at),
                        count,
                        self.cfg.num_target_views,
                        pick,
                    )
                continue
            try:
                example = decode_scene_example(item, draws.reader, pick, self.cfg, rng)
            except Exception as e:  # noqa: BLE001 - one bad sample must never stop a multi-day run
                self._count("corrupt_samples")
                log.warning("skipping corrupt sample %s in %s: %s (counted in corrupt_samples)", key, shard, e)
                continue
            draws.accepted += 1
            return example


@dataclass
class _Draws:
    """What one training iterator has drawn so far: passes over the scenes without a usable example, usable
    examples in the current pass, the scene lengths seen and the (scene, reason) skips already logged; and the
    reader of its frames."""

    reader: FrameReader
    barren_passes: int = 0
    accepted: int = 0
    lengths: set[int] = field(default_factory=set)
    named: set[tuple[str, str]] = field(default_factory=set)


class EvalStream(_ShardStream):
    """Deterministic, complete evaluation stream: each sample exactly once across ranks x workers.

    With at least as many shards as (ranks x workers) whole shards are dealt out; otherwise every worker
    reads every shard and keeps the samples whose running index falls to it.
    """

    def __init__(
        self, shards: list[str], cfg: StreamConfig, rank: int, world_size: int, counters: Tensor
    ) -> None:
        super().__init__(cfg, rank, world_size, counters)
        if not shards:
            raise ValueError("no shards to stream")
        self.shards = sorted(str(s) for s in shards)

    def splits(self, worker: int, num_workers: int) -> tuple[list[str], int | None, int]:
        """(shards to read, modulus or None, residue) for one worker of this rank."""
        total = self.world_size * num_workers
        me = self.rank * num_workers + worker
        if len(self.shards) >= total:
            return self.shards[me::total], None, me
        return self.shards, total, me

    def _decode(self, shard: str, key: str, raw: dict) -> Example | None:
        try:
            return decode_evaluation_sample(raw, self.cfg)
        except NoContext as e:
            self._count("no_context_views")
            log.warning("skipping evaluation sample %s in %s: %s (counted in no_context_views)", key, shard, e)
        except TooFewTargets as e:
            self._count("too_few_targets")
            log.warning("skipping evaluation sample %s in %s: %s (counted in too_few_targets)", key, shard, e)
        except Exception as e:  # noqa: BLE001 - one bad sample must never stop an evaluation
            self._count("corrupt_samples")
            log.warning("skipping corrupt sample %s in %s: %s (counted in corrupt_samples)", key, shard, e)
        return None

    def __iter__(self) -> Iterator[BatchedExample]:
        """Batches of ``batch_size`` samples that share their numbers of context and target views and whether
        they carry highlight masks (a batch is one tensor); each group's last batch may be smaller."""
        wid, nw = _worker()
        shards, modulus, me = self.splits(wid, nw)
        pending: dict[tuple[int, int, bool], list[Example]] = {}
        i = -1
        for shard in shards:
            for key, raw in self._samples(shard):
                i += 1
                if modulus is not None and i % modulus != me:
                    continue
                example = self._decode(shard, key, raw)
                if example is None:
                    continue
                kind = (example.num_context, example.images.shape[0] - example.num_context,
                        example.highlight is not None)  # fmt: skip
                batch = pending.setdefault(kind, [])
                batch.append(example)
                if len(batch) == self.cfg.batch_size:
                    yield collate(pending.pop(kind))
        for batch in pending.values():
            yield collate(batch)


def counter_totals(counters: Tensor) -> dict[str, int]:
    """Sum a counter table over workers -> {name: count}."""
    totals = counters.sum(0).tolist()
    return dict(zip(COUNTERS, (int(t) for t in totals)))


def sample_keys(batch: BatchedExample) -> list[tuple[str, tuple[int, ...]]]:
    """(scene, frame ids) per batch element: identifies samples in tests and logs."""
    frames = torch.cat([batch.context.index, batch.target.index], dim=1).tolist()
    return [(s, tuple(f)) for s, f in zip(batch.scene, frames)]


def usable_at(frames: int, allowed: tuple[int, int], cfg: StreamConfig, count: int) -> bool:
    """Whether a scene of ``frames`` frames can give a fresh example in the ``allowed`` gap range."""
    return gap_range(frames, allowed, smallest_gap(count, cfg.num_target_views or 1, cfg.min_target_distance)) \
        is not None  # fmt: skip
