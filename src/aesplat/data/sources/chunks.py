"""pixelSplat-style chunks (RealEstate10K, ACID, the synthetic set): ``SRC/{train,validation,test}/*.torch``.

Each chunk is a list of scenes ``{key, cameras float32[F, 18], images: list of JPEG byte tensors, ...}``
(:mod:`aesplat.data.pixelsplat_chunks`); a unit is one chunk file. A scene's optional ``specular`` [F, H, W]
(the synthetic set's specular magnitude) is passed on for the highlight masks of evaluation samples.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ...errors import MissingFileError
from ..pixelsplat_chunks import CAMERA_ROW, jpeg_bytes, list_chunks, load_chunk, row_to_cameras
from ..scene import Scene, Skipped
from .base import SPLITS, SourceConfig, Unit, read_info


@dataclass(frozen=True)
class ChunkReader:
    """Reads ``src/<split>/*.torch`` (the chunks ``index.json`` names, else every one)."""

    src: Path
    cfg: SourceConfig

    def info(self) -> dict[str, Any]:
        return read_info(self.src)

    def units(self) -> list[Unit]:
        units = [Unit(split, chunk.stem, chunk) for split in SPLITS if (self.src / split).is_dir()
                 for chunk in list_chunks(self.src / split)]  # fmt: skip
        if not any((self.src / split).is_dir() for split in SPLITS):
            raise MissingFileError(
                f"{self.src} holds no train/ or test/ folder of *.torch chunks (pixelSplat layout)"
            )
        return units

    def keys(self, unit: Unit) -> list[str]:
        index = unit.path.parent / "index.json"
        if index.is_file():
            return _keys_by_chunk(index, index.stat().st_mtime_ns).get(unit.path.name, [])
        try:
            scenes = load_chunk(unit.path)
        except ValueError:
            return []  # reported as a corrupt chunk when the unit is converted
        return [str(s["key"]) for s in scenes if isinstance(s, dict) and "key" in s]

    def dataset(self) -> str:
        return self.cfg.dataset or str(self.info().get("dataset", self.src.name))

    def scenes(self, unit: Unit) -> Iterator[Scene | Skipped]:
        try:
            chunk = load_chunk(unit.path)
        except ValueError as err:
            yield Skipped("", "corrupt_chunk", str(err).splitlines()[0])
            return
        dataset = self.dataset()
        for i, entry in enumerate(chunk):
            yield scene_from_entry(entry, i, dataset, unit.path)


@lru_cache(maxsize=4)
def _keys_by_chunk(index: Path, mtime_ns: int) -> dict[str, list[str]]:
    """A split's ``index.json`` (key -> chunk file) inverted: chunk file -> sorted keys (read once per file)."""
    out: dict[str, list[str]] = {}
    for key, chunk in json.loads(index.read_text()).items():
        out.setdefault(chunk, []).append(key)
    return {chunk: sorted(keys) for chunk, keys in out.items()}


def scene_from_entry(entry: Any, position: int, dataset: str, source: Path) -> Scene | Skipped:
    """One chunk entry -> a typed scene, or what makes it unreadable (``missing_field``, ``bad_camera``,
    ``corrupt_image``)."""
    if not isinstance(entry, dict) or not all(k in entry for k in ("key", "cameras", "images")):
        key = str(entry.get("key", "")) if isinstance(entry, dict) else ""
        return Skipped(
            key or f"#{position}",
            "missing_field",
            f"{key or f'scene #{position}'}: a chunk scene needs key, cameras and images",
        )
    key = str(entry["key"])
    rows = np.asarray(entry["cameras"], dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != CAMERA_ROW or rows.shape[0] != len(entry["images"]):
        return Skipped(key, "bad_camera", f"{key}: cameras of shape {tuple(rows.shape)} for "
                       f"{len(entry['images'])} images; one row of {CAMERA_ROW} numbers per frame")  # fmt: skip
    images = [jpeg_bytes(im) for im in entry["images"]]
    sizes = []
    for f, data in enumerate(images):  # header reads only: cheap
        try:
            with Image.open(io.BytesIO(data)) as im:
                sizes.append(im.size)
        except Exception:  # noqa: BLE001 - any unreadable header means a corrupt image
            return Skipped(key, "corrupt_image", f"{key}: frame {f} is not a readable image")
    c2w, k = row_to_cameras(rows)
    specular = entry.get("specular")
    if specular is not None:
        specular = np.asarray(specular, dtype=np.float32)
        if specular.shape[0] != len(images):
            return Skipped(key, "bad_specular", f"{key}: specular holds {specular.shape[0]} frames, the scene "
                           f"{len(images)}")  # fmt: skip
    return Scene(key, dataset, c2w, k, images, sizes, specular=specular, sources=[source])
