"""Data: synthetic scenes, chunk -> shard conversion, shard streaming and the DataModule (SPEC section 6)."""

from .curriculum import GapCurriculum
from .datamodule import DataModule
from .shards import convert_dataset, verify_shards
from .stream import flip_views
from .synthetic import generate_dataset, render_scene, sample_scene

__all__ = [
    "DataModule",
    "GapCurriculum",
    "convert_dataset",
    "flip_views",
    "generate_dataset",
    "render_scene",
    "sample_scene",
    "verify_shards",
]
