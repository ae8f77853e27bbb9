"""Source readers: one per source format, each yielding typed scenes (docs/data.md, docs/captures.md).

A reader lists its source's *units* (a chunk file, a scene folder: each becomes one shard per split), the scene
keys of a unit without reading its images, and the unit's scenes as :class:`~aesplat.data.scene.Scene` objects
in this project's convention (or :class:`~aesplat.data.scene.Skipped` records with a reason). The writer
(:mod:`aesplat.data.convert`) does everything else, the same way for every format. A new source format is one
new module here and one entry in :data:`READERS`.
"""

from __future__ import annotations

from pathlib import Path

from ...errors import UserError
from .base import SPLITS, Reader, SourceConfig, Unit, read_info
from .chunks import ChunkReader
from .colmap import ColmapReader
from .nerfstudio import NerfstudioReader

READERS: dict[str, type] = {"chunks": ChunkReader, "nerfstudio": NerfstudioReader, "colmap": ColmapReader}

__all__ = ["READERS", "SPLITS", "Reader", "SourceConfig", "Unit", "make_reader", "read_info"]


def make_reader(src: str | Path, cfg: SourceConfig) -> Reader:
    """The reader of ``cfg.fmt`` over the source folder ``src``."""
    if cfg.fmt not in READERS:
        raise UserError(f"unknown source format {cfg.fmt!r}; choose from {sorted(READERS)}")
    return READERS[cfg.fmt](Path(src), cfg)
