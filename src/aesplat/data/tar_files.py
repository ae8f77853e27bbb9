"""WebDataset tar files: the shard writer, the sample reader, and the index of whole-scene shards whose frames
are read only when picked."""

from __future__ import annotations

import io
import json
import os
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .layout import FRAME_OFFSETS, FRAMES, META


class ShardWriter:
    """A WebDataset tar written sample by sample under ``NAME.tar.tmp`` (fixed mtime: reproducible checksums),
    flushed to disk and renamed to ``NAME.tar`` by :meth:`commit`: a reader never sees half a shard. Leaving
    the ``with`` block without a commit (an error, a full disk) removes the temporary file."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_suffix(".tar.tmp")
        self.samples = 0
        self._file = open(self.tmp, "wb")  # noqa: SIM115 - closed by commit or __exit__
        self._tar = tarfile.open(fileobj=self._file, mode="w", format=tarfile.USTAR_FORMAT)

    def add(self, key: str, sample: dict[str, bytes]) -> None:
        for ext, data in sample.items():
            info = tarfile.TarInfo(f"{key}.{ext}")
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            self._tar.addfile(info, io.BytesIO(data))
        self.samples += 1

    def commit(self) -> None:
        self._tar.close()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self.tmp, self.path)

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self._file.closed:
            try:
                self._tar.close()
                self._file.close()
            except OSError:
                pass  # the disk that failed the write may fail the close as well; the file goes anyway
            self.tmp.unlink(missing_ok=True)


def _samples(path: str | Path, stream: bool) -> Iterator[tuple[str, dict[str, Any]]]:
    """(key, {extension: bytes}) of each sample of a tar, members grouped by key. ``stream``: read in order
    (``r|``); else random access, where ``frames.jpgs`` stays on disk as (byte offset, length). Raises
    ``tarfile.ReadError`` / ``EOFError`` / ``OSError`` on a truncated or corrupt tar (the incomplete sample at
    the point of failure is never yielded, wherever the file was cut)."""
    key, sample = None, {}
    size = os.path.getsize(path)
    with tarfile.open(path, "r|" if stream else "r:") as tar:
        for member in tar:
            if not member.isfile():
                continue
            k, _, ext = member.name.rsplit("/", 1)[-1].partition(".")
            if not stream and member.offset_data + member.size > size:
                raise tarfile.ReadError(f"member {member.name} truncated")
            if stream or ext != FRAMES:
                data = tar.extractfile(member).read()
                if len(data) != member.size:
                    raise tarfile.ReadError(f"member {member.name} truncated")
            else:
                data = (member.offset_data, member.size)
            if k != key:
                if key is not None:
                    yield key, sample
                key, sample = k, {}
            sample[ext] = data
        # tarfile ends quietly when the file stops inside a header: a whole archive ends with two zero blocks.
        if size - tar.offset < 2 * tarfile.BLOCKSIZE:
            raise tarfile.ReadError(f"archive truncated after {tar.offset} bytes (no end-of-archive marker)")
    if key is not None:
        yield key, sample


def read_tar(path: str | Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """Stream the samples of a WebDataset tar: (key, {extension: bytes}) (see :func:`_samples`)."""
    yield from _samples(path, stream=True)


@dataclass(frozen=True)
class SceneEntry:
    """A whole-scene sample as indexed, not read: its small members' bytes (meta, cameras, frame offsets) and
    where its frames' JPEGs lie in the shard (byte offset and length of ``frames.jpgs``)."""

    shard: str
    key: str
    members: dict[str, bytes]
    frames_at: int
    frames_size: int

    @property
    def num_frames(self) -> int:
        return len(json.loads(self.members[META])["frames"])


def index_scenes(path: str | Path) -> Iterator[SceneEntry]:
    """The whole-scene samples of a training shard, reading only the headers and the small members: the frames
    stay on disk until an example picks some (:class:`FrameReader`). Errors as :func:`_samples`."""
    for key, members in _samples(path, stream=False):
        span = members.pop(FRAMES, None)
        if span is not None:
            yield SceneEntry(str(path), key, members, *span)


class FrameReader:
    """Reads a scene's picked frames from its shard, keeping the last few shards open (one reader per worker:
    it is made empty in each process)."""

    def __init__(self, keep: int = 8) -> None:
        self.keep = keep
        self._open: dict[str, Any] = {}

    def frames(self, entry: SceneEntry, picks: list[int]) -> list[bytes]:
        offsets = np.load(io.BytesIO(entry.members[FRAME_OFFSETS]))
        if offsets[-1] != entry.frames_size or (np.diff(offsets) <= 0).any():
            raise ValueError(
                f"frame offsets {offsets[:3]}… do not describe {entry.frames_size} bytes of frames"
            )
        f = self._open.pop(entry.shard, None) or open(entry.shard, "rb")  # noqa: SIM115 - kept open, closed below
        self._open[entry.shard] = f  # most recently used last
        while len(self._open) > self.keep:
            self._open.pop(next(iter(self._open))).close()
        out = []
        for v in picks:
            f.seek(entry.frames_at + int(offsets[v]))
            data = f.read(int(offsets[v + 1] - offsets[v]))
            if len(data) != offsets[v + 1] - offsets[v]:
                raise ValueError(f"frame {v} is cut short in {entry.shard}")
            out.append(data)
        return out
