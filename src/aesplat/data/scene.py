"""The typed scene every source reader yields and the conversion writes (docs/data.md).

A reader (``aesplat.data.sources``) turns one source format into :class:`Scene` objects in this project's
convention; everything after it (the validation layer, the shard writer) sees only these.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class SceneError(ValueError):
    """A scene that cannot be converted: ``reason`` is a short code (counted in the manifest), the message one
    line naming the problem and the fix."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class Scene:
    """One source scene, its frames in the source's order.

    key: the scene's name (chunk key or scene folder name); dataset: the data set's name (sample meta)
    c2w: float64 [F, 4, 4] camera-to-world, OpenCV axes, in the scene's own world frame
    intrinsics: float64 [F, 3, 3] normalised (fx, cx / width; fy, cy / height) for the frames as read
    images: F encoded frames (JPEG or PNG bytes), read on access
    sizes: (width, height) of every frame as read
    names: the frames' names as the source writes them (captures: file paths), else None
    files: the image file of every frame where the source has files (captures), else None
    specular: float [F, H, W] magnitude of the scene's specular term (synthetic scenes), else None
    sources: the files the scene was read from; a rerun reconverts it when one of them changed
    """

    key: str
    dataset: str
    c2w: np.ndarray
    intrinsics: np.ndarray
    images: Sequence[bytes]
    sizes: list[tuple[int, int]]
    names: list[str] | None = None
    files: list[Path] | None = None
    specular: np.ndarray | None = None
    sources: list[Path] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)


@dataclass(frozen=True)
class Skipped:
    """What a reader yields instead of a scene it cannot read: ``key`` (empty for a whole unreadable source
    file), a reason code and a one-line message."""

    key: str
    reason: str
    message: str
