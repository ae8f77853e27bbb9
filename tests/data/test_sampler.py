"""The view sampler's pure functions: bounded draws, the fixed pool, counts per batch, evaluation contexts."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from aesplat.data.sampler import (
    ContextCount,
    evaluation_context,
    evaluation_sample,
    fixed_pool,
    gap_range,
    sample_views,
    smallest_gap,
)


@pytest.mark.parametrize("k", [2, 3, 4, 5, 6])
def test_k_context_views_are_ordered_distinct_inside_and_targets_lie_between(k):
    rng = np.random.default_rng(k)
    frames, allowed, vt = 40, (8, 30), 3
    gaps = set()
    for _ in range(300):
        pick = sample_views(frames, allowed, k, vt, 1, rng)
        c = pick.context
        assert len(c) == k and list(c) == sorted(set(c))  # ordered and distinct
        assert 0 <= c[0] and c[-1] < frames and allowed[0] <= pick.gap <= allowed[1]
        assert len(pick.target) == vt and len(set(pick.target)) == vt
        assert all(c[0] < t < c[-1] and t not in c for t in pick.target)
        gaps.add(pick.gap)
    assert min(gaps) == 8 and max(gaps) == 30  # the whole range is drawn, both ends included


def test_min_distance_keeps_targets_away_from_the_outer_context_views():
    rng = np.random.default_rng(0)
    for _ in range(200):
        pick = sample_views(30, (10, 20), 2, 2, 4, rng)
        assert all(pick.context[0] + 4 <= t <= pick.context[-1] - 4 for t in pick.target)
    # Room: k - 2 extras and the targets within [c0 + d, c1 - d], whatever frames the extras take.
    assert smallest_gap(2, 1, 1) == 2 and smallest_gap(6, 3, 1) == 8 and smallest_gap(2, 2, 4) == 9
    worst = [sample_views(smallest_gap(k, 3, 2) + 1, (0, 99), k, 3, 2, np.random.default_rng(s))
             for k in (2, 4, 6) for s in range(50)]  # fmt: skip
    assert all(len(p.target) == 3 for p in worst)


def test_gaps_are_clipped_to_the_scene_and_a_scene_too_short_gives_none():
    assert gap_range(12, (5, 21), 2) == (5, 11)
    assert gap_range(5, (5, 21), 2) is None  # 5 frames: the largest gap is 4
    assert gap_range(30, (5, 21), 9) == (9, 21)  # four extra views and three targets need a gap of 9
    assert gap_range(8, (2, 6), 9) is None
    assert sample_views(5, (5, 21), 2, 1, 1, np.random.default_rng(0)) is None
    short = [sample_views(12, (5, 21), 2, 1, 1, np.random.default_rng(s)).gap for s in range(200)]
    assert min(short) == 5 and max(short) == 11


def test_the_start_and_the_targets_are_spread_not_degenerate():
    rng = np.random.default_rng(1)
    picks = [sample_views(50, (10, 10), 2, 1, 1, rng) for _ in range(2000)]
    starts = Counter(p.context[0] for p in picks)
    assert set(starts) == set(range(40))  # every start 0..39 occurs
    assert max(starts.values()) < 3 * min(starts.values())
    offsets = Counter(p.target[0] - p.context[0] for p in picks)
    assert set(offsets) == set(range(1, 10))


def test_fixed_pool_is_drawn_once_per_scene_over_the_whole_span():
    pool = fixed_pool(40, (5, 21), 8, 2, 3, 1, seed=7)
    assert pool == fixed_pool(40, (5, 21), 8, 2, 3, 1, seed=7)  # the same pool every time
    assert pool != fixed_pool(40, (5, 21), 8, 2, 3, 1, seed=8)
    gaps = [p.gap for p in pool]
    assert gaps[0] == 5 and len(pool) == 8 and max(gaps) >= 19  # stratified over the span, smallest first
    assert all(len(p.target) == 3 and all(p.context[0] < t < p.context[1] for t in p.target) for p in pool)
    assert len(fixed_pool(40, (2, 21), 4, 2, 3, 1, seed=0)[0].target) == 1  # a gap of 2 holds one target
    assert fixed_pool(4, (5, 21), 8, 2, 3, 1, seed=0) == []


def test_context_count_per_batch_is_deterministic_from_seed_and_step():
    count = ContextCount.parse([2, 6])
    draws = [count.at(0, step) for step in range(400)]
    assert draws == [count.at(0, step) for step in range(400)]  # a resumed run draws the same counts
    assert set(draws) == {2, 3, 4, 5, 6}
    assert draws != [count.at(1, step) for step in range(400)]
    assert ContextCount.parse(3).at(5, 17) == 3 and ContextCount.parse(3).fixed
    for bad in (1, [3, 2], [2], "2", [1, 4], True):
        with pytest.raises(ValueError, match="num_context_views"):
            ContextCount.parse(bad)


def test_evaluation_contexts_are_deterministic_and_avoid_the_targets():
    context, target = (10, 30), (15, 20, 25)
    assert evaluation_context(context, target, 2) == (10, 30)
    assert evaluation_context(context, target, 3) == (10, 19, 30)  # 20 is a target: the nearest free below
    four = evaluation_context(context, target, 4)
    assert four == (10, 17, 23, 30)
    six = evaluation_context(context, target, 6)
    assert len(six) == 6 and list(six) == sorted(set(six)) and not set(six) & set(target)
    assert evaluation_context((30, 10), target, 3) == (30, 19, 10)  # view 0 stays the index's first frame
    assert evaluation_context((4, 8), (5, 6, 7), 3) is None  # no free frame between
    assert evaluation_context((1, 5, 9), (3,), 3) == (1, 5, 9)  # an index entry of k views is kept
    # An index of more views listed pair first, extras after: other counts span the pair, view 0 first.
    assert evaluation_context((10, 30, 17, 23), target, 2) == (10, 30)
    assert evaluation_context((30, 10, 17, 23), target, 3) == (30, 19, 10)
    assert evaluation_sample(8, 5, 3) == ((1, 6), (2, 4, 5))
    assert evaluation_sample(30, 3, 5)[1] == (14, 15)  # only two frames lie between
