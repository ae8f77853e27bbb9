"""Shared fixtures: one small synthetic data set and its shards, built once per test session."""

from __future__ import annotations

import pytest

from aesplat.data import convert_dataset, generate_dataset

FRAMES = 12
HEIGHT, WIDTH = 48, 64
SIZE = 28


@pytest.fixture(scope="session")
def synthetic_src(tmp_path_factory):
    out = tmp_path_factory.mktemp("synthetic")
    generate_dataset(out, scenes=6, test_scenes=5, frames=FRAMES, height=HEIGHT, width=WIDTH, seed=3,
                     scenes_per_chunk=2)  # fmt: skip
    return out


@pytest.fixture(scope="session")
def synthetic_shards(synthetic_src, tmp_path_factory):
    out = tmp_path_factory.mktemp("shards")
    convert_dataset(synthetic_src, out, size=SIZE, progress=False)
    return out
