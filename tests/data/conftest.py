"""Shared fixtures: one small synthetic data set and its shards, built once per test session."""

from __future__ import annotations

import shutil

import pytest

from tests.data.servers import TOKEN
from tests.helpers import make_shards, need
from tests.script_loader import load_script

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


@pytest.fixture(scope="module")
def local_nginx():
    module = load_script("local_nginx")
    try:
        module.nginx_binary()
    except SystemExit:
        need(False, "nginx")
    return module


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """Shards of 4 training scenes (one a shard) and 2 test scenes, which ``server`` serves."""
    return make_shards(tmp_path_factory.mktemp("served"), scenes=4, test_scenes=2, seed=1, scenes_per_chunk=1)


@pytest.fixture
def server(local_nginx, served, tmp_path):
    """An nginx serving a copy of ``served`` (a test may change it), stopped after the test."""
    root = tmp_path / "root"
    shutil.copytree(served, root)
    with local_nginx.Nginx(root, tmp_path / "nginx", token=TOKEN) as nginx:
        yield nginx
