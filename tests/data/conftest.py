"""Shared fixtures: one small synthetic data set and its shards, built once per test session."""

from __future__ import annotations

import pytest

from tests.helpers import make_shards

FRAMES = 12
HEIGHT, WIDTH = 48, 64
SIZE = 28


@pytest.fixture(scope="session")
def synthetic_shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    return make_shards(root, SIZE, FRAMES, HEIGHT, WIDTH, scenes=6, test_scenes=5, seed=3, scenes_per_chunk=2)


@pytest.fixture(scope="session")
def synthetic_src(synthetic_shards):
    """The source chunks of ``synthetic_shards``."""
    return synthetic_shards.parent / "src"
