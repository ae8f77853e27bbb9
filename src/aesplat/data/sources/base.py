"""What every source reader shares: its options, its units and the protocol the writer relies on."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ...errors import UserError
from ..scene import Scene, Skipped

SPLITS = ("train", "validation", "test")


@dataclass(frozen=True)
class SourceConfig:
    """How a source is read (the reader options of ``to_shards.py``).

    fmt: a key of :data:`aesplat.data.sources.READERS`; dataset: the name written into every sample
    (default: the source's ``dataset.json``, else its folder name). Folder formats (one folder per scene):
    split: the split every scene goes to; capture_path: the transforms file / model folder relative to a
    scene (default: found); images: the image folder (nerfstudio: replaces the first folder of ``file_path``;
    COLMAP: relative to the scene, default ``images``); frame_order: ``name`` or ``file`` (nerfstudio only;
    COLMAP frames are sorted by name)."""

    fmt: str = "chunks"
    dataset: str | None = None
    split: str = "test"
    capture_path: str | None = None
    images: str | None = None
    frame_order: str = "name"

    def __post_init__(self) -> None:
        if self.split not in ("train", "test"):
            raise UserError(f"split must be train or test, got {self.split!r}")
        if self.frame_order not in ("name", "file"):
            raise UserError(f"frame_order must be 'name' or 'file', got {self.frame_order!r}")


@dataclass(frozen=True)
class Unit:
    """One source file or folder of a split; it becomes the shard ``<split>-<name>.tar``."""

    split: str
    name: str
    path: Path


class Reader(Protocol):
    """What the writer needs from a source format."""

    src: Path
    cfg: SourceConfig

    def info(self) -> dict[str, Any]:
        """The source's description (``dataset.json`` of a chunk source: name, gap range), else ``{}``."""

    def units(self) -> list[Unit]:
        """Every unit of every split present, in a fixed order (a one-line error if there is none)."""

    def keys(self, unit: Unit) -> list[str]:
        """The scene keys of a unit, without reading images (for holding scenes out as validation)."""

    def scenes(self, unit: Unit) -> Iterator[Scene | Skipped]:
        """The unit's scenes, in order; what cannot be read is a :class:`Skipped` record, never an exception."""


def read_info(src: Path) -> dict[str, Any]:
    """``src/dataset.json`` (written by ``data_prep/synthetic.py``), or ``{}``."""
    path = src / "dataset.json"
    if not path.is_file():
        return {}
    try:
        info = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return info if isinstance(info, dict) else {}
