"""Streaming shards into ``BatchedExample`` batches, split explicitly by rank and worker (docs/data.md).

- Training: every (rank, worker) resamples its shards forever through a shuffle buffer and yields exactly its
  share of ``batches_per_rank`` batches, so every rank sees the same number of batches (no DDP hang).
  Epochs are blocks of ``batches_per_rank`` global steps. Batch j of the epoch that starts at step e is drawn
  for step e + j: the curriculum judges its samples at that step, and the random streams are seeded with e.
  So the data depend only on (seed, rank, e, j), not on timing or prefetching, and an iterator started in
  the middle of an epoch (a run resumed from a mid-epoch checkpoint) replays the epoch's first batches
  without yielding them and continues exactly where the interrupted run stopped.
- Evaluation: deterministic order, every sample exactly once across all ranks and workers.
- A corrupt sample or shard is skipped, counted in a shared counter table and logged, never fatal.

Workers batch samples themselves (the DataLoader runs with ``batch_size=None``) so batch counts are exact.
"""

from __future__ import annotations

import io
import json
import logging
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from aesplat.types import BatchedExample, BatchedViews

from .curriculum import GapCurriculum

log = logging.getLogger("aesplat.data")

COUNTERS = ("corrupt_samples", "corrupt_shards", "curriculum_skipped", "too_few_targets")
REFLECT = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))


def new_counters(num_workers: int) -> Tensor:
    """Shared-memory counter table [workers + 1, len(COUNTERS)]: one row per worker (row 0 = main process),
    so workers never write the same cell."""
    return torch.zeros(num_workers + 1, len(COUNTERS), dtype=torch.int64).share_memory_()


def read_tar(path: str | Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """Stream the samples of a WebDataset tar: (key, {extension: bytes}), members grouped by key.

    Raises ``tarfile.ReadError`` / ``EOFError`` / ``OSError`` on a truncated or corrupt tar (the incomplete
    sample at the point of failure is never yielded).
    """
    key, sample = None, {}
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
    if key is not None:
        yield key, sample


def flip_views(images: Tensor, extrinsics: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Mirror views horizontally and the world with them: images [..., 3, H, W], camera-to-world [..., 4, 4],
    normalised intrinsics [..., 3, 3]. Pixel u maps to W - u; a world point X maps to diag(-1, 1, 1) X."""
    intrinsics = intrinsics.clone()
    intrinsics[..., 0, 2] = 1.0 - intrinsics[..., 0, 2]
    reflect = REFLECT.to(extrinsics)
    return images.flip(-1), reflect @ extrinsics @ reflect, intrinsics


@dataclass(frozen=True)
class StreamConfig:
    """What a stream needs to turn samples into batches (built by the DataModule)."""

    image_size: int
    batch_size: int
    num_context_views: int = 2
    num_target_views: int | None = 1  # None: every target of the sample (evaluation)
    flip_augment: bool = False


def decode_sample(key: str, raw: dict[str, bytes], cfg: StreamConfig, rng: np.random.Generator | None) -> dict:
    """Raw sample -> tensors. ``rng`` picks the targets (a sorted random subset) and the flip; None means
    evaluation: every target (or the first ``num_target_views``), no flip. ``ValueError`` on a bad sample.
    ``highlight`` is the picked targets' masks bool [Vt, 1, H, W] when the sample has one for each of them
    (``tgtI.spec.png``), else None; resized by nearest neighbour and flipped with the images."""
    meta = json.loads(raw["meta.json"])
    ctx_names = sorted(
        (n for n in raw if n.startswith("ctx") and n.endswith(".jpg")), key=lambda n: int(n[3:-4])
    )
    tgt_names = sorted(
        (n for n in raw if n.startswith("tgt") and n.endswith(".jpg")), key=lambda n: int(n[3:-4])
    )
    if len(ctx_names) != cfg.num_context_views:
        raise ValueError(
            f"sample has {len(ctx_names)} context views, the data module wants {cfg.num_context_views}"
        )
    extrinsics = torch.from_numpy(np.load(io.BytesIO(raw["extrinsics.npy"]))).float()
    intrinsics = torch.from_numpy(np.load(io.BytesIO(raw["intrinsics.npy"]))).float()
    v = len(ctx_names) + len(tgt_names)
    if extrinsics.shape != (v, 4, 4) or intrinsics.shape != (v, 3, 3):
        raise ValueError(
            f"camera arrays {tuple(extrinsics.shape)}, {tuple(intrinsics.shape)} do not match {v} views"
        )
    want = len(tgt_names) if cfg.num_target_views is None else cfg.num_target_views
    if len(tgt_names) < want:
        raise ValueError(f"sample has {len(tgt_names)} targets, the data module wants {want}")
    if rng is None:
        picked = list(range(want))
    else:
        picked = sorted(rng.choice(len(tgt_names), size=want, replace=False).tolist())
    views = list(range(len(ctx_names))) + [len(ctx_names) + i for i in picked]
    names = ctx_names + [tgt_names[i] for i in picked]
    images = []
    for name in names:
        with Image.open(io.BytesIO(raw[name])) as pil:
            img = torch.from_numpy(np.array(pil.convert("RGB"))).permute(2, 0, 1)  # [3, H, W] uint8
        if img.shape[1:] != (cfg.image_size, cfg.image_size):
            if img.shape[1] != img.shape[2]:
                raise ValueError(f"{name} is {tuple(img.shape[1:])}, shard images must be square")
            # Square to square maps the full extent onto the full extent: normalised intrinsics are unchanged.
            img = F.interpolate(img[None].float(), size=(cfg.image_size,) * 2, mode="bilinear", antialias=True,
                                align_corners=False)[0].round().clamp(0, 255).to(torch.uint8)  # fmt: skip
        images.append(img)
    images_t = torch.stack(images)  # [V, 3, H, W]
    highlight = _highlight(raw, [tgt_names[i] for i in picked], cfg.image_size)
    extrinsics, intrinsics = extrinsics[views], intrinsics[views]
    frames = torch.tensor(list(meta["context"]) + [meta["target"][i] for i in picked], dtype=torch.int64)
    if not (torch.isfinite(extrinsics).all() and torch.isfinite(intrinsics).all()):
        raise ValueError("non-finite cameras")
    if rng is not None and cfg.flip_augment and rng.uniform() < 0.5:
        images_t, extrinsics, intrinsics = flip_views(images_t, extrinsics, intrinsics)
        highlight = None if highlight is None else highlight.flip(-1)
    overlap = meta.get("overlap")
    return {
        "key": key,
        "images": images_t,
        "extrinsics": extrinsics,
        "intrinsics": intrinsics,
        "index": frames,
        "scene": str(meta["scene"]),
        "dataset": str(meta.get("dataset", "")),
        "gap": int(meta["gap"]),
        "overlap": float("nan") if overlap is None else float(overlap),
        "highlight": highlight,
    }


def _highlight(raw: dict[str, bytes], targets: list[str], size: int) -> Tensor | None:
    """Highlight masks of the named target images (``tgtI.jpg`` -> ``tgtI.spec.png``): bool [Vt, 1, S, S], or
    None unless every one of them has a mask."""
    names = [name[: -len(".jpg")] + ".spec.png" for name in targets]
    if not names or not all(n in raw for n in names):
        return None
    masks = []
    for name in names:
        with Image.open(io.BytesIO(raw[name])) as pil:
            mask = torch.from_numpy(np.array(pil.convert("L")) > 127)[None]  # [1, H, W]
        if mask.shape[-1] != mask.shape[-2]:
            raise ValueError(f"{name} is {tuple(mask.shape[1:])}, shard masks must be square")
        if mask.shape[-1] != size:  # nearest keeps it a mask; the image's resize is an antialiased bilinear
            mask = F.interpolate(mask[None].float(), size=(size, size), mode="nearest-exact")[0] > 0.5
        masks.append(mask)
    return torch.stack(masks)


def collate(samples: list[dict], cfg: StreamConfig) -> BatchedExample:
    """Decoded samples -> ``BatchedExample`` with uint8 images [B, V, 3, H, W]."""
    nc = cfg.num_context_views

    def views(sl: slice) -> BatchedViews:
        images = torch.stack([s["images"][sl] for s in samples])
        return BatchedViews(
            images=images,
            extrinsics=torch.stack([s["extrinsics"][sl] for s in samples]),
            intrinsics=torch.stack([s["intrinsics"][sl] for s in samples]),
            index=torch.stack([s["index"][sl] for s in samples]),
        )

    counts = sorted({s["images"].shape[0] - nc for s in samples})
    if len(counts) > 1:
        raise ValueError(
            f"samples of one batch have different numbers of target views {counts} (scenes "
            f"{[s['scene'] for s in samples]}): set eval_num_target_views or eval_batch_size=1"
        )
    with_masks = [s.get("highlight") is not None for s in samples]
    if any(with_masks) and not all(with_masks):
        raise ValueError(
            f"only some samples of one batch have highlight masks (scenes {[s['scene'] for s in samples]}): "
            "evaluate shards with and without masks separately, or set eval_batch_size=1"
        )
    return BatchedExample(
        context=views(slice(0, nc)),
        target=views(slice(nc, None)),
        scene=[s["scene"] for s in samples],
        overlap=torch.tensor([s["overlap"] for s in samples], dtype=torch.float32),
        gap=torch.tensor([s["gap"] for s in samples], dtype=torch.int64),
        dataset=[s["dataset"] for s in samples],
        highlight=torch.stack([s["highlight"] for s in samples]) if all(with_masks) else None,
    )


def _worker() -> tuple[int, int]:
    info = get_worker_info()
    return (0, 1) if info is None else (info.id, info.num_workers)


class _ShardStream(IterableDataset):
    """Shared plumbing: shard list, rank, counters and safe reading."""

    def __init__(
        self, shards: list[str], cfg: StreamConfig, rank: int, world_size: int, counters: Tensor
    ) -> None:
        super().__init__()
        if not shards:
            raise ValueError("no shards to stream")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is outside world size {world_size}")
        self.shards = sorted(str(s) for s in shards)
        self.cfg = cfg
        self.rank = rank
        self.world_size = world_size
        self.counters = counters

    def _count(self, what: str, n: int = 1) -> None:
        info = get_worker_info()
        row = 0 if info is None else min(info.id + 1, self.counters.shape[0] - 1)  # one row per process
        self.counters[row, COUNTERS.index(what)] += n

    def _samples(self, shard: str) -> Iterator[tuple[str, dict[str, bytes]]]:
        try:
            yield from read_tar(shard)
        except (tarfile.TarError, EOFError, OSError, ValueError) as e:
            self._count("corrupt_shards")
            log.warning("skipping the rest of corrupt shard %s: %s (counted in corrupt_shards)", shard, e)

    def _decode(self, shard: str, key: str, raw: dict, rng: np.random.Generator | None) -> dict | None:
        try:
            return decode_sample(key, raw, self.cfg, rng)
        except Exception as e:  # noqa: BLE001 - one bad sample must never stop a multi-day run
            self._count("corrupt_samples")
            log.warning("skipping corrupt sample %s in %s: %s (counted in corrupt_samples)", key, shard, e)
            return None


class TrainStream(_ShardStream):
    """Infinite resampled training stream cut to ``batches_per_rank`` batches per rank (per epoch).

    step: shared int64 [1] tensor holding the global step; read when an epoch's iterator starts. Epochs are
    blocks of ``batches_per_rank`` steps, so a step inside a block means "resume this epoch here".
    """

    def __init__(self, shards: list[str], cfg: StreamConfig, rank: int, world_size: int, counters: Tensor,
                 step: Tensor, curriculum: GapCurriculum, batches_per_rank: int, seed: int = 0,
                 shuffle_buffer: int = 64) -> None:  # fmt: skip
        super().__init__(shards, cfg, rank, world_size, counters)
        if batches_per_rank < 1:
            raise ValueError(f"train_batches_per_epoch must be >= 1, got {batches_per_rank}")
        self.step = step
        self.curriculum = curriculum
        self.batches_per_rank = batches_per_rank
        self.seed = seed
        self.shuffle_buffer = max(1, shuffle_buffer)

    def __len__(self) -> int:
        return self.batches_per_rank

    def worker_shards(self, worker: int, num_workers: int) -> list[str]:
        """This rank's shards for one worker. With fewer shards than ranks (or workers) every rank (worker)
        reads them all; their random streams differ, which is harmless for training."""
        mine = self.shards[self.rank :: self.world_size] if len(self.shards) >= self.world_size else self.shards
        return mine[worker::num_workers] if len(mine) >= num_workers else mine

    def _raw_forever(
        self, shards: list[str], rng: np.random.Generator
    ) -> Iterator[tuple[str, str, dict] | None]:
        """Shuffled raw samples forever; ``None`` marks the end of each pass over the shards."""
        buffer: list[tuple[str, str, dict]] = []
        while True:
            yielded = read = 0
            for shard in rng.permutation(shards).tolist():
                for key, raw in self._samples(shard):
                    buffer.append((shard, key, raw))
                    read += 1
                    if len(buffer) >= self.shuffle_buffer:
                        yield buffer.pop(int(rng.integers(len(buffer))))
                        yielded += 1
            if yielded == 0 and not buffer:
                raise RuntimeError(f"training shards {shards} hold no readable samples")
            # Keep at most half a buffer, and never more than half a pass: with fewer samples than the buffer
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
        shards = self.worker_shards(role, nw)
        rng = np.random.default_rng([self.seed, self.rank, role, start])
        raw_stream = self._raw_forever(shards, rng)
        draws = _Draws()
        for j in range(role, self.batches_per_rank, nw):  # this stream's batches of the epoch
            at = start + j  # the global step batch j is trained at
            batch = [self._next_sample(raw_stream, rng, at, draws) for _ in range(self.cfg.batch_size)]
            if j >= done:  # earlier batches are replayed (their samples drew from rng) but not yielded
                yield collate(batch, self.cfg)

    def _next_sample(self, raw_stream: Iterator, rng: np.random.Generator, at: int, draws: _Draws) -> dict:
        """The next sample the curriculum allows at step ``at`` that decodes."""
        while True:
            item = next(raw_stream)
            if item is None:  # end of a pass: two in a row without one usable sample cannot recover
                draws.barren_passes = 0 if draws.accepted else draws.barren_passes + 1
                draws.accepted = 0
                if draws.barren_passes >= 2:
                    seen = sorted(draws.gaps_seen)[:20]
                    raise RuntimeError(
                        f"no training sample has a context gap allowed by the curriculum at step {at} "
                        f"({self.curriculum.allowed(at)}) or decodes; gaps seen: {seen}. "
                        "Convert with a matching --min-gap/--max-gap or change the curriculum ranges."
                    )
                continue
            shard, key, raw = item
            try:  # filter on the metadata before decoding any image
                meta = json.loads(raw["meta.json"])
                gap, targets = int(meta["gap"]), len(meta["target"])
            except Exception:  # noqa: BLE001
                gap = targets = None  # decode_sample counts it as corrupt
            if gap is not None and not self.curriculum.accepts(gap, at):
                self._count("curriculum_skipped")
                draws.gaps_seen.add(gap)
                continue
            if targets is not None and targets < (self.cfg.num_target_views or 1):
                self._count("too_few_targets")
                continue
            sample = self._decode(shard, key, raw, rng)
            if sample is not None:
                draws.accepted += 1
                return sample


@dataclass
class _Draws:
    """What one training iterator has drawn so far: passes over the shards without a usable sample, usable
    samples in the current pass, and the gaps the curriculum turned down (for the error message)."""

    barren_passes: int = 0
    accepted: int = 0
    gaps_seen: set[int] = field(default_factory=set)


class EvalStream(_ShardStream):
    """Deterministic, complete evaluation stream: each sample exactly once across ranks x workers.

    With at least as many shards as (ranks x workers) whole shards are dealt out; otherwise every worker
    reads every shard and keeps the samples whose running index falls to it.
    """

    def splits(self, worker: int, num_workers: int) -> tuple[list[str], int | None, int]:
        """(shards to read, modulus or None, residue) for one worker of this rank."""
        total = self.world_size * num_workers
        me = self.rank * num_workers + worker
        if len(self.shards) >= total:
            return self.shards[me::total], None, me
        return self.shards, total, me

    def __iter__(self) -> Iterator[BatchedExample]:
        wid, nw = _worker()
        shards, modulus, me = self.splits(wid, nw)
        batch: list[dict] = []
        i = -1
        for shard in shards:
            for key, raw in self._samples(shard):
                i += 1
                if modulus is not None and i % modulus != me:
                    continue
                sample = self._decode(shard, key, raw, None)
                if sample is None:
                    continue
                batch.append(sample)
                if len(batch) == self.cfg.batch_size:
                    yield collate(batch, self.cfg)
                    batch = []
        if batch:
            yield collate(batch, self.cfg)


def counter_totals(counters: Tensor) -> dict[str, int]:
    """Sum a counter table over workers -> {name: count}."""
    totals = counters.sum(0).tolist()
    return dict(zip(COUNTERS, (int(t) for t in totals)))


def sample_keys(batch: BatchedExample) -> list[tuple[str, tuple[int, ...]]]:
    """(scene, frame ids) per batch element: identifies samples in tests and logs."""
    frames = torch.cat([batch.context.index, batch.target.index], dim=1).tolist()
    return [(s, tuple(f)) for s, f in zip(batch.scene, frames)]
