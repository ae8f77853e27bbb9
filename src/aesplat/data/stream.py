"""The training and evaluation streams: shards -> ``BatchedExample`` batches, split by rank and worker
explicitly (docs/data.md).

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

import logging
import tarfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from aesplat.types import BatchedExample, Example, StepTracker

from .curriculum import GapCurriculum
from .decode import (
    NoContext,
    StreamConfig,
    TooFewTargets,
    collate,
    decode_evaluation_sample,
    decode_scene_example,
)
from .layout import safe_key
from .manifest import SceneRef, partition
from .sampler import ViewSampler
from .tar_files import FrameReader, SceneEntry, index_scenes, read_tar

log = logging.getLogger("aesplat.data")

COUNTERS = ("corrupt_samples", "corrupt_shards", "curriculum_skipped", "too_few_targets", "scene_too_short",
            "too_few_between", "no_context_views")  # fmt: skip


def new_counters(num_workers: int) -> Tensor:
    """Shared-memory counter table [workers + 1, len(COUNTERS)]: one row per worker (row 0 = main process),
    so workers never write the same cell."""
    return torch.zeros(num_workers + 1, len(COUNTERS), dtype=torch.int64).share_memory_()


def _worker() -> tuple[int, int]:
    info = get_worker_info()
    return (0, 1) if info is None else (info.id, info.num_workers)


class _ShardStream(IterableDataset):
    """Shared plumbing: rank, counters and safe reading. ``fetch``: called on a shard's path before it is
    opened, where the shards come from a URL (:meth:`aesplat.data.remote.RemoteShards.fetch`: the shard is
    downloaded and verified in the process that reads it, or fails the run in one line, never skipped)."""

    def __init__(self, cfg: StreamConfig, rank: int, world_size: int, counters: Tensor,
                 fetch: Callable[[str], str] | None = None) -> None:  # fmt: skip
        super().__init__()
        self.cfg = cfg
        self.rank = rank
        self.world_size = world_size
        self.counters = counters
        self.fetch = fetch

    def _count(self, what: str, n: int = 1) -> None:
        info = get_worker_info()
        row = 0 if info is None else min(info.id + 1, self.counters.shape[0] - 1)  # one row per process
        self.counters[row, COUNTERS.index(what)] += n

    def _samples(self, shard: str, scenes: bool = False) -> Iterator:
        """The samples of a shard (``scenes``: indexed :class:`SceneEntry` objects); a corrupt shard is
        abandoned at the point of damage, counted and logged."""
        if self.fetch is not None:
            shard = self.fetch(shard)
        try:
            yield from index_scenes(shard) if scenes else read_tar(shard)
        except (tarfile.TarError, EOFError, OSError, ValueError) as e:
            self._count("corrupt_shards")
            log.warning("skipping the rest of corrupt shard %s: %s (counted in corrupt_shards)", shard, e)


class TrainStream(_ShardStream):
    """Infinite training stream over whole scenes, cut to ``batches_per_rank`` batches per rank (per epoch).

    scenes: this rank's training scenes (:func:`partition` of :func:`aesplat.data.manifest.training_scenes`);
    sampler: their examples' views; step: the global step, read when an epoch's iterator starts. Epochs are
    blocks of ``batches_per_rank`` steps, so a step inside a block means "resume this epoch here".
    """

    def __init__(self, scenes: list[SceneRef], cfg: StreamConfig, sampler: ViewSampler, rank: int,
                 world_size: int, counters: Tensor, step: StepTracker, curriculum: GapCurriculum,
                 batches_per_rank: int, seed: int = 0, shuffle_buffer: int = 64,
                 fetch: Callable[[str], str] | None = None) -> None:  # fmt: skip
        super().__init__(cfg, rank, world_size, counters, fetch)
        if batches_per_rank < 1:
            raise ValueError(f"train_batches_per_epoch must be >= 1, got {batches_per_rank}")
        self.scenes = scenes
        self.sampler = sampler
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
        step = self.step.get()
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
            pick = self.sampler.draw(frames, key, self.curriculum.allowed(at), count, rng)
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

    def __init__(self, shards: list[str], cfg: StreamConfig, rank: int, world_size: int, counters: Tensor,
                 fetch: Callable[[str], str] | None = None) -> None:  # fmt: skip
        super().__init__(cfg, rank, world_size, counters, fetch)
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
