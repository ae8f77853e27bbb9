"""Which frames of a scene make an example: the bounded view sampler of training, the fixed-pool variant, the
count of context views per step, and the deterministic k-view evaluation contexts (docs/data.md).

Training (the paper's recipe, NAS3R's bounded sampler): a context gap drawn uniformly from the curriculum's
range at the current step (clipped to the scene), a random first context frame, ``k - 2`` extra context frames
drawn between the outer two, targets drawn between the outer two at least ``min_distance`` frames from them and
never on a context frame. Everything here is a pure function of its arguments and a ``numpy`` generator.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

POOL_TARGETS = 3  # targets stored per fixed-pool example, as the pre-drawn samples of earlier shards held


@dataclass(frozen=True)
class ViewPick:
    """Frame indices (positions in the scene's frame order) of one example: ``context`` ascending, the outer
    two first and last; ``target`` ascending, strictly between them."""

    context: tuple[int, ...]
    target: tuple[int, ...]

    @property
    def gap(self) -> int:
        return self.context[-1] - self.context[0]


def smallest_gap(num_context: int, num_targets: int, min_distance: int) -> int:
    """The smallest context gap that always leaves room for ``num_context - 2`` extra context frames and
    ``num_targets`` targets at least ``min_distance`` (>= 1) frames from the outer context frames."""
    extras = num_context - 2
    return max(extras + 1, 2 * min_distance - 1 + num_targets + extras)


def gap_range(num_frames: int, allowed: tuple[int, int], need: int) -> tuple[int, int] | None:
    """The gaps a scene of ``num_frames`` frames can give inside the curriculum's ``allowed`` range [lo, hi] and
    at least ``need``; None if there is none."""
    lo, hi = max(allowed[0], need), min(allowed[1], num_frames - 1)
    return (lo, hi) if lo <= hi else None


def views_with_gap(num_frames: int, gap: int, num_context: int, num_targets: int, min_distance: int,
                   rng: np.random.Generator) -> ViewPick:  # fmt: skip
    """An example with context gap ``gap`` (which must leave room: :func:`smallest_gap`): a random start, the
    extra context frames and then the targets drawn without repetition."""
    c0 = int(rng.integers(0, num_frames - gap))
    c1 = c0 + gap
    extras = rng.choice(np.arange(c0 + 1, c1), size=num_context - 2, replace=False) if num_context > 2 else []
    context = (c0, *sorted(int(e) for e in extras), c1)
    free = np.setdiff1d(np.arange(c0 + min_distance, c1 - min_distance + 1), context)
    target = rng.choice(free, size=num_targets, replace=False)
    return ViewPick(context, tuple(sorted(int(t) for t in target)))


def sample_views(num_frames: int, allowed: tuple[int, int], num_context: int, num_targets: int,
                 min_distance: int, rng: np.random.Generator) -> ViewPick | None:  # fmt: skip
    """One training example of a scene: the gap uniform over :func:`gap_range`; None when the scene cannot
    give one in the allowed range."""
    gaps = gap_range(num_frames, allowed, smallest_gap(num_context, num_targets, min_distance))
    if gaps is None:
        return None
    gap = int(rng.integers(gaps[0], gaps[1] + 1))
    return views_with_gap(num_frames, gap, num_context, num_targets, min_distance, rng)


def scene_seed(seed: int, key: str) -> int:
    """A seed of one scene's own (its fixed pool), from the run's seed and the scene key only."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{key}".encode()).digest()[:8], "little")


def fixed_pool(num_frames: int, span: tuple[int, int], size: int, num_context: int, num_targets: int,
               min_distance: int, seed: int) -> list[ViewPick]:  # fmt: skip
    """``size`` examples of a scene drawn once (``seed``: :func:`scene_seed`) for the whole run: the
    pre-drawn samples of a conversion, as the fixed-pool arm of the learning-effect measurement uses them.

    Gaps are stratified over ``span`` (the curriculum's whole range, clipped to the scene) so the pool covers
    every phase of the curriculum; the first example always has the smallest gap. Each holds up to
    ``num_targets`` targets. Empty when the scene cannot give a gap in ``span``."""
    gaps = gap_range(num_frames, span, smallest_gap(num_context, 1, min_distance))
    if gaps is None:
        return []
    lo, hi = gaps
    rng = np.random.default_rng(seed)
    edges = np.linspace(lo, hi + 1, size + 1)
    pool = []
    for i in range(size):
        gap = lo if i == 0 else int(np.clip(np.floor(rng.uniform(edges[i], edges[i + 1])), lo, hi))
        room = gap - 2 * min_distance + 1 - (num_context - 2)  # targets that always fit
        pool.append(views_with_gap(num_frames, gap, num_context, min(num_targets, room), min_distance, rng))
    return pool


@dataclass(frozen=True)
class ViewSampler:
    """The views of training examples, and the one rule of which scenes can give them: fresh examples
    (:func:`sample_views`), or with ``fixed_pool`` N > 0 one of N examples per scene drawn once
    (:func:`fixed_pool` over the curriculum's whole ``span``, seeded by ``seed`` and the scene key).

    num_targets: targets per example; min_distance: frames a target keeps from the outer context frames."""

    num_targets: int
    min_distance: int
    fixed_pool: int = 0
    span: tuple[int, int] = (0, 0)
    seed: int = 0

    def pool(self, frames: int, key: str, count: int) -> list[ViewPick]:
        return fixed_pool(frames, self.span, self.fixed_pool, count, POOL_TARGETS, self.min_distance,
                          scene_seed(self.seed, key))  # fmt: skip

    def unusable(self, frames: int, key: str, allowed: tuple[int, int], count: int) -> str | None:
        """None when a scene of ``frames`` frames can give an example with a context gap in ``allowed`` and
        ``count`` context views; else why not, as the stream's counter names it."""
        if not self.fixed_pool:
            if gap_range(frames, allowed, smallest_gap(count, self.num_targets, self.min_distance)) is not None:
                return None
            return "scene_too_short" if frames - 1 < allowed[0] else "too_few_between"
        return self._pool_unusable(self.pool(frames, key, count), allowed)

    def _pool_unusable(self, pool: list[ViewPick], allowed: tuple[int, int]) -> str | None:
        if not pool:
            return "scene_too_short"
        options = [p for p in pool if allowed[0] <= p.gap <= allowed[1]]
        if not options:
            return "curriculum_skipped"
        return None if any(len(p.target) >= self.num_targets for p in options) else "too_few_targets"

    def draw(self, frames: int, key: str, allowed: tuple[int, int], count: int,
             rng: np.random.Generator) -> ViewPick | str:  # fmt: skip
        """One example of a scene, or why it gives none now (:meth:`unusable`; ``too_few_targets`` when the
        pool example drawn holds too few targets)."""
        if not self.fixed_pool:
            pick = sample_views(frames, allowed, count, self.num_targets, self.min_distance, rng)
            return pick if pick is not None else self.unusable(frames, key, allowed, count) or "too_few_targets"
        pool = self.pool(frames, key, count)  # drawn once: the reason below reads the same pool
        options = [p for p in pool if allowed[0] <= p.gap <= allowed[1]]
        if options:
            chosen = options[int(rng.integers(len(options)))]
            if len(chosen.target) >= self.num_targets:
                targets = rng.choice(np.array(chosen.target), size=self.num_targets, replace=False)
                return ViewPick(chosen.context, tuple(sorted(int(t) for t in targets)))
        return self._pool_unusable(pool, allowed) or "too_few_targets"


@dataclass(frozen=True)
class ContextCount:
    """How many context views each training batch has: a fixed number, or a range [lo, hi] from which every
    batch draws its own count, the same for all its samples, deterministically from the seed and the step
    (so a resumed run draws the same counts, and every rank the same one)."""

    lo: int
    hi: int

    @classmethod
    def parse(cls, value: int | tuple[int, int] | list[int]) -> ContextCount:
        """``2``, or ``[2, 6]``; a one-line ``ValueError`` for anything else."""
        if isinstance(value, int) and not isinstance(value, bool):
            lo = hi = value
        elif isinstance(value, (tuple, list)) and len(value) == 2 and all(isinstance(v, int) for v in value):
            lo, hi = value
        else:
            raise ValueError(f"data.num_context_views takes a number or a range [lo, hi], got {value!r}")
        if not 2 <= lo <= hi:
            raise ValueError(f"data.num_context_views needs 2 <= lo <= hi, got {value!r}")
        return cls(int(lo), int(hi))

    @property
    def fixed(self) -> bool:
        return self.lo == self.hi

    def at(self, seed: int, step: int) -> int:
        """The count of the batch trained at global ``step``."""
        if self.fixed:
            return self.lo
        return int(np.random.default_rng([seed, step, 0xC0]).integers(self.lo, self.hi + 1))


def evaluation_sample(num_frames: int, gap: int, num_targets: int) -> tuple[tuple[int, int], tuple[int, ...]]:
    """The deterministic evaluation sample of a scene without an index entry: context frames ``gap`` apart
    centred in the sequence, up to ``num_targets`` distinct targets evenly spaced strictly between them."""
    c0 = (num_frames - 1 - gap) // 2
    inner = np.linspace(c0, c0 + gap, num_targets + 2)[1:-1]
    targets = sorted({int(np.clip(round(t), c0 + 1, c0 + gap - 1)) for t in inner})
    return (c0, c0 + gap), tuple(targets)


def evaluation_context(context: tuple[int, ...], target: tuple[int, ...], k: int) -> tuple[int, ...] | None:
    """The k context views of an evaluation sample whose index gives ``context`` and ``target``: the index's own
    when it has k views; otherwise its outermost context frames (the lowest and the highest) with ``k - 2``
    frames evenly spaced between them, each moved to the nearest frame that is neither a target nor already
    taken (the lower one on a tie). None when too few frames lie between. View 0 is the outer frame nearer the
    index's first context frame (the frame itself, for a pair or a context listed pair first)."""
    if len(context) == k:
        return tuple(context)
    lo, hi = min(context), max(context)
    taken = set(target) | {lo, hi}
    extras: list[int] = []
    for j in range(1, k - 1):
        want = lo + (hi - lo) * j / (k - 1)
        candidates = sorted((f for f in range(lo + 1, hi) if f not in taken), key=lambda f: (abs(f - want), f))
        if not candidates:
            return None
        extras.append(candidates[0])
        taken.add(candidates[0])
    frames = (lo, *sorted(extras), hi)
    return frames if context[0] - lo <= hi - context[0] else frames[::-1]
