"""What the capture formats share: one folder per scene, image files on disk, lenses undistorted on reading.

A unit is a scene folder (``SRC/<scene>/``); every scene goes to the split the options name. The frames' images
are read (and undistorted) only when the writer asks for them (:class:`FrameImages`).
"""

from __future__ import annotations

import io
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from ...errors import MissingFileError, UserError
from ..layout import safe_key
from ..lens import Camera, normalized_intrinsics, pinhole_camera, undistort, undistortion_map
from ..scene import Scene, SceneError, Skipped
from .base import SourceConfig, Unit


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) from an image file's header; ``missing_image`` / ``corrupt_image`` if unreadable."""
    if not path.is_file():
        raise SceneError("missing_image", f"{what}: image {path} does not exist; restore it or drop the frame")
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - any unreadable header is a corrupt image
        raise SceneError("corrupt_image", f"{what}: image {path} cannot be read; replace it") from None


def find_one(scene: Path, pattern: str, what: str) -> Path:
    """The one file or folder under ``scene`` matching ``pattern`` (its top level first, then any depth)."""
    found = sorted(scene.glob(pattern)) or sorted(scene.rglob(pattern))
    if len(found) != 1:
        detail = "none" if not found else ", ".join(str(p.relative_to(scene)) for p in found[:4])
        raise SceneError("missing_capture_file", f"{what}: expected one {pattern} under {scene}, found "
                         f"{detail}; name it with --capture-path")  # fmt: skip
    return found[0]


class FrameImages(Sequence):
    """The frames' images as encoded bytes, read (and undistorted) on access.

    A pinhole frame is the file's own bytes; an undistorted frame is an uncompressed PNG of the pinhole image
    (lossless; decoded again at once). The undistortion map is computed once per camera."""

    def __init__(self, paths: list[Path], cameras: list[Camera]) -> None:
        self.paths, self.cameras = paths, cameras
        self._maps: dict[Camera, tuple[float, torch.Tensor]] = {}

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> bytes:  # type: ignore[override]
        path, camera = self.paths[i], self.cameras[i]
        if not camera.distorted:
            return path.read_bytes()
        if camera not in self._maps:
            zoom = pinhole_camera(camera)[1]
            self._maps[camera] = zoom, undistortion_map(camera, zoom)
        zoom, uv = self._maps[camera]
        with Image.open(path) as im:
            out = undistort(im, camera, zoom, uv)
        buf = io.BytesIO()
        out.save(buf, format="PNG", compress_level=0)
        return buf.getvalue()


def capture_scene(key: str, dataset: str, names: list[str], paths: list[Path], c2w: list[np.ndarray],
                  cameras: list[Camera], capture_files: list[Path]) -> Scene:  # fmt: skip
    """A typed scene from a capture's frames: undistorted frames carry their pinhole (zoomed) intrinsics."""
    pinhole: dict[Camera, Camera] = {}
    ks = []
    for cam in cameras:
        if cam not in pinhole:  # one zoom search per distinct camera, not per frame
            pinhole[cam] = pinhole_camera(cam)[0]
        ks.append(normalized_intrinsics(pinhole[cam]))
    sizes = [(c.width, c.height) for c in cameras]
    return Scene(key, dataset, np.stack(c2w), np.stack(ks), FrameImages(paths, cameras), sizes, names=names,
                 files=paths, sources=[*capture_files, *paths])  # fmt: skip


@dataclass(frozen=True)
class FolderReader(ABC):
    """Units are the scene folders of ``src`` (hidden ones left out), all in ``cfg.split``; a subclass reads
    one folder into a scene (:meth:`read`)."""

    src: Path
    cfg: SourceConfig

    def info(self) -> dict[str, Any]:
        return {}

    def units(self) -> list[Unit]:
        if not self.src.is_dir():
            raise MissingFileError(f"{self.src} is not a folder; --src must hold one folder per scene")
        folders = sorted(p for p in self.src.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not folders:
            raise MissingFileError(f"{self.src} holds no scene folder; --src must hold one folder per scene")
        names: dict[str, str] = {}
        for folder in folders:
            clash = names.setdefault(safe_key(folder.name), folder.name)
            if clash != folder.name:
                raise UserError(
                    f"scene folders {clash!r} and {folder.name!r} differ only in characters a shard "
                    "name cannot hold; rename one"
                )
        return [Unit(self.cfg.split, safe_key(p.name), p) for p in folders]

    def keys(self, unit: Unit) -> list[str]:
        return [unit.path.name]

    def dataset(self) -> str:
        return self.cfg.dataset or self.src.name

    def scenes(self, unit: Unit) -> Iterator[Scene | Skipped]:
        try:
            yield self.read(unit.path)
        except SceneError as err:
            name = unit.path.name
            message = str(err) if str(err).startswith(f"{name}:") else f"{name}: {err}"
            yield Skipped(name, err.reason, message)

    @abstractmethod
    def read(self, folder: Path) -> Scene:
        """One scene folder -> its scene; ``SceneError`` if it cannot be converted."""
