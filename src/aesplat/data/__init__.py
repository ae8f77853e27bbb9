"""Data: synthetic scenes, chunk -> shard conversion, shard streaming and the DataModule (docs/data.md).

``DataModule`` is imported lazily: the data-preparation scripts never pay for importing Lightning.
"""

from typing import TYPE_CHECKING

from .capture_shards import convert_captures
from .curriculum import GapCurriculum
from .shards import convert_dataset, verify_shards
from .stream import flip_views
from .synthetic_scenes import generate_dataset, render_scene, sample_scene

if TYPE_CHECKING:
    from .datamodule import DataModule

__all__ = [
    "DataModule",
    "GapCurriculum",
    "convert_captures",
    "convert_dataset",
    "flip_views",
    "generate_dataset",
    "render_scene",
    "sample_scene",
    "verify_shards",
]


def __getattr__(name: str):
    if name == "DataModule":
        from .datamodule import DataModule

        return DataModule
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
