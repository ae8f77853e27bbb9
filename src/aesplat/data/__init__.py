"""Data: synthetic scenes, the conversion pipeline (a reader per source format, one shard writer), the run-time
view sampler, shard streaming and the DataModule (docs/data.md).

``DataModule`` is imported lazily: the data-preparation scripts never pay for importing Lightning.
"""

from typing import TYPE_CHECKING

from .convert import convert_dataset
from .curriculum import GapCurriculum
from .decode import flip_views
from .manifest import read_manifest, verify_shards
from .synthetic_scenes import generate_dataset, render_scene, sample_scene

if TYPE_CHECKING:
    from .datamodule import DataModule

__all__ = ["DataModule", "GapCurriculum", "convert_dataset", "flip_views", "generate_dataset", "read_manifest",
           "render_scene", "sample_scene", "verify_shards"]  # fmt: skip


def __getattr__(name: str):
    if name == "DataModule":
        from .datamodule import DataModule

        return DataModule
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
