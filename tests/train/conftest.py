"""Shared fixtures: a tiny synthetic shard set (two training shards, one test shard) built once per session."""

import pytest

from aesplat.data import convert_dataset, generate_dataset

# The smoke data: 28x28 views; context gaps 2..8 frames; depth range 0.1..20 (see conf/smoke.yaml).
SHARD_SIZE = 28


@pytest.fixture(scope="session")
def smoke_shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("smoke_data")
    generate_dataset(root / "src", scenes=4, test_scenes=2, frames=12, height=48, width=64, seed=0,
                     scenes_per_chunk=2)  # fmt: skip
    convert_dataset(root / "src", root / "shards", size=SHARD_SIZE)
    return root / "shards"
