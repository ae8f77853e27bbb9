"""``manifest.json``: what a shard folder holds, read as a typed record (docs/data.md).

The manifest's ``version`` says which layout the folder holds: 1, pre-drawn samples in every split (written
before training drew its views from whole scenes); 2, whole scenes in ``train`` (layout ``scenes``) and
deterministic samples in ``validation`` / ``test`` (layout ``samples``). Every reader of a shard folder
(:func:`find_shards`, :func:`has_split`, :func:`training_scenes`, :func:`verify_shards`) goes through
:func:`read_manifest`, so a damaged manifest, an old layout or a folder of tars that are not shards is one
line naming the fix, never a traceback or an empty run.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import re
import tarfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import MissingFileError, UserError

MANIFEST_VERSION = 2
LAYOUTS = ("scenes", "samples")
CONVERT = "python data_prep/to_shards.py"

log = logging.getLogger("aesplat.data")


def sha256(path: Path, follow_links: bool = True) -> str:
    """The SHA-256 of the file ``path``; with ``follow_links`` False, of that file itself and never of one a
    link there leads to (``OSError`` for a link)."""
    h = hashlib.sha256()
    flags = os.O_RDONLY | os.O_CLOEXEC | (0 if follow_links else os.O_NOFOLLOW)
    with os.fdopen(os.open(path, flags), "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class ShardRecord:
    """One shard of a split: its file name, checksum (lower case), (training shards) its scenes' frame counts,
    and its size in bytes (None in manifests that do not give it)."""

    shard: str
    sha256: str | None
    samples: int = 0
    scene_frames: dict[str, int] = field(default_factory=dict)
    size: int | None = None


@dataclass(frozen=True)
class SplitRecord:
    """One split: ``scenes`` (whole scenes, training) or ``samples`` (deterministic samples), its shards, and
    for evaluation splits the largest number of context views its samples carry contexts for and how many of
    its samples carry each number of targets (``{3: 12}``; empty when the manifest does not say)."""

    layout: str
    shards: list[ShardRecord]
    context_views: int = 2
    target_counts: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Manifest:
    """The typed ``manifest.json``; ``data`` keeps the whole file (counts, skips, options) for reports."""

    version: int
    source: str
    splits: dict[str, SplitRecord]
    data: dict[str, Any]

    @property
    def size(self) -> int | None:
        return self.data.get("config", {}).get("size")


def _damaged(path: Path, why: str) -> UserError:
    return UserError(f"{path} is damaged ({why}); convert again with `{CONVERT} --src SRC --out {path.parent}` "
                     "(finished shards are kept)")  # fmt: skip


# What a manifest may name: a split is a folder, a shard a file in it, both in the converter's own characters
# (letters, digits, ``.``, ``_``, ``-``; never ``/``, never a leading ``.``), so that no name read from a
# manifest, a server's included, reaches outside the shard folder.
SPLIT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
SHARD_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,195}\.tar")
DIGEST = re.compile(r"[0-9a-fA-F]{64}")


def _whole(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _split(name: str, entry: Any, version: int, damaged: Callable[[str], UserError]) -> SplitRecord:
    if not isinstance(entry, dict) or not isinstance(entry.get("shards"), list):
        raise damaged(f"split {name!r} has no list of shards")
    layout = entry.get("layout", "samples") if version >= 2 else "samples"
    if layout not in LAYOUTS:
        raise damaged(f"split {name!r} has an unknown layout {layout!r}")
    shards = []
    for item in entry["shards"]:
        if not isinstance(item, dict) or not isinstance(item.get("shard"), str):
            raise damaged(f"split {name!r} lists a shard without a file name")
        shard = item["shard"]
        if not SHARD_NAME.fullmatch(shard):
            raise damaged(f"split {name!r} lists the shard {shard[:80]!r}, which is not a file name of "
                          "letters, digits, '.', '_' and '-' ending in .tar")  # fmt: skip
        digest, size = item.get("sha256"), item.get("bytes")
        if digest is not None and not (isinstance(digest, str) and DIGEST.fullmatch(digest)):
            raise damaged(f"split {name!r}: shard {shard} has the sha256 {str(digest)[:80]!r}, not 64 "
                          "hexadecimal digits")  # fmt: skip
        if size is not None and not _whole(size):
            raise damaged(
                f"split {name!r}: shard {shard} has the size {str(size)[:80]!r}, not a number of bytes"
            )
        if not _whole(item.get("samples", 0)):
            raise damaged(f"split {name!r}: shard {shard} has a malformed count of samples")
        frames = item.get("scene_frames") or {}
        if not isinstance(frames, dict) or not all(_whole(v) for v in frames.values()):
            raise damaged(f"split {name!r}: shard {shard} has malformed scene_frames")
        shards.append(ShardRecord(shard, digest and digest.lower(), item.get("samples", 0), frames, size))
    if len({s.shard for s in shards}) < len(shards):
        raise damaged(f"split {name!r} lists a shard twice")
    samples = entry.get("evaluation_samples") if version >= 2 else None
    targets: dict[int, int] = {}
    for sample in samples.values() if isinstance(samples, dict) else ():
        if not isinstance(sample, dict) or not isinstance(sample.get("target"), list):
            raise damaged(f"split {name!r} lists an evaluation sample without targets")
        targets[len(sample["target"])] = targets.get(len(sample["target"]), 0) + 1
    context_views = entry.get("context_views", 2) if version >= 2 else 2
    if not _whole(context_views) or context_views < 1:
        raise damaged(f"split {name!r} has a malformed number of context views")
    return SplitRecord(layout, shards, context_views, targets)


def parse_manifest(text: str | bytes, where: str, damaged: Callable[[str], UserError]) -> Manifest:
    """A manifest's text as a :class:`Manifest`, every name, digest and count checked; ``where`` names it in
    messages, ``damaged(why)`` is the error for a malformed one."""
    try:
        data = json.loads(text)
    except (UnicodeDecodeError, ValueError, RecursionError) as err:  # ValueError: JSON's, and overlong numbers
        raise damaged(f"not valid JSON: {str(err)[:200]}") from None
    if not isinstance(data, dict) or not isinstance(data.get("splits"), dict):
        raise damaged("no `splits` object")
    version = data.get("version", 1)
    if not isinstance(version, int) or not 1 <= version <= MANIFEST_VERSION:
        raise UserError(f"{where} has version {str(version)[:40]!r}; this aesplat reads versions 1 to "
                        f"{MANIFEST_VERSION}: update aesplat or convert the source again")  # fmt: skip
    for name in data["splits"]:
        if not SPLIT_NAME.fullmatch(name):
            raise damaged(f"the split {name[:80]!r} is not a folder name of letters, digits, '.', '_' and '-'")
    splits = {name: _split(name, entry, version, damaged) for name, entry in data["splits"].items()}
    source = data.get("source")  # quoted in messages: one printable line or nothing
    source = source if isinstance(source, str) and source.isprintable() and len(source) < 300 else "SRC"
    return Manifest(version, source, splits, data)


def read_manifest(root: str | Path) -> Manifest | None:
    """``root/manifest.json`` as a :class:`Manifest`; None when there is none; a ``UserError`` when it is
    unreadable or malformed."""
    path = Path(root) / "manifest.json"
    if not path.is_file():
        return None
    try:
        text = path.read_bytes()
    except OSError as err:
        raise _damaged(path, f"unreadable: {err.strerror or err}") from None
    return parse_manifest(text, str(path), functools.partial(_damaged, path))


def data_digest(manifest: Manifest) -> str:
    """The SHA-256 of what ``manifest`` says the data are: every split's shards by name and SHA-256 (not its
    counts or dates), to tell whether two runs, or two ranks, read the same data."""
    lines = sorted(
        f"{name}/{s.shard} {s.sha256}" for name, split in manifest.splits.items() for s in split.shards
    )
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def has_split(root: str | Path, split: str) -> bool:
    """Whether the shards under ``root`` hold ``split``: the manifest lists it, or (without one) its folder
    has tars."""
    manifest = read_manifest(root)
    if manifest is not None:
        return split in manifest.splits
    return any((Path(root) / split).glob("*.tar"))


def probe_shard(path: Path) -> None:
    """Refuse (``UserError``) a tar whose first sample is not a shard sample of this project (no
    ``KEY.meta.json``, no images), or a file that is not a tar archive."""
    why = None
    try:
        with tarfile.open(path, "r|") as tar:
            key, names = None, set()
            for member in tar:
                k, _, ext = member.name.rsplit("/", 1)[-1].partition(".")
                if key is not None and k != key:
                    break
                key = k
                names.add(ext)
    except (tarfile.TarError, EOFError, OSError) as err:
        why = f"not a readable tar archive: {err}"
    else:
        if key is None:
            why = "an empty archive"
        elif "meta.json" not in names:
            why = f"its first sample {key} has no meta.json"
        elif not any(n.endswith((".jpg", ".jpgs")) for n in names):
            why = f"its first sample {key} has no images"
    if why is not None:
        raise UserError(f"{path} is not a shard of aesplat ({why}); make shards with `{CONVERT} --src SRC "
                        f"--out {path.parent.parent}`")  # fmt: skip


def find_shards(root: str | Path, split: str, fetched_later: bool = False) -> list[str]:
    """Sorted shard paths of ``root/<split>``: those the manifest lists if there is one (stale tars from an
    older conversion are ignored), else every ``*.tar``, each checked to be a shard. A one-line error naming
    the fix if there are none, or they are not shards. ``fetched_later``: ``root`` is the cache of a URL
    (:mod:`aesplat.data.remote`), whose shards are fetched, and checked against the manifest's SHA-256, when
    read: every shard the manifest lists, none probed."""
    root = Path(root)
    if fetched_later:
        listed = read_manifest(root).splits.get(split)
        if listed is None or not listed.shards:
            raise MissingFileError(f"no {split} shards listed in the manifest.json of {root}")
        return sorted(str(root / split / s.shard) for s in listed.shards)
    if not root.is_dir():
        raise MissingFileError(
            f"no shards in {root}: the folder does not exist; give the folder `{CONVERT} --out` wrote, or "
            "create it with that command"
        )
    folder = root / split
    manifest = read_manifest(root)
    listed = None if manifest is None else manifest.splits.get(split)
    if listed is not None:
        wanted = [folder / s.shard for s in listed.shards]
        found = sorted(str(p) for p in wanted if p.exists())
        if len(found) < len(wanted):
            log.warning("%d shards listed in %s are missing from %s", len(wanted) - len(found), root, folder)
        probes = found[:1]
    else:
        found = sorted(str(p) for p in folder.glob("*.tar"))
        probes = found  # a folder of tars nobody described: each must be a shard
    if not found:
        raise MissingFileError(
            f"no shards in {folder}: create them with `{CONVERT} --src SRC --out {root}` (or `python "
            "data_prep/synthetic.py --out SRC` first for the synthetic set)"
        )
    for path in probes:
        probe_shard(Path(path))
    return found


@dataclass(frozen=True)
class SceneRef:
    """One training scene: the shard holding it, its key and its number of stored frames."""

    shard: str
    key: str
    frames: int


def partition(scenes: list[SceneRef], part: int, parts: int) -> list[SceneRef]:
    """Part ``part`` of ``parts`` disjoint parts of ``scenes`` (sorted by shard): whole shards dealt out when
    there are at least as many shards as parts (each shard read by one part only), else scenes dealt out."""
    shards = sorted({s.shard for s in scenes})
    if len(shards) >= parts:
        mine = set(shards[part::parts])
        return [s for s in scenes if s.shard in mine]
    return scenes[part::parts]


def training_scenes(root: str | Path, fetched_later: bool = False) -> list[SceneRef]:
    """Every training scene of the shards under ``root``, by shard then key. Shards of pre-drawn samples
    (manifest version 1) are refused with the command that converts their source again. ``fetched_later``:
    as :func:`find_shards`."""
    root = Path(root)
    shards = find_shards(root, "train", fetched_later)
    manifest = read_manifest(root)
    if manifest is None:
        raise MissingFileError(f"no manifest.json in {root}: training reads the scene list `{CONVERT}` writes "
                               f"there; convert with `{CONVERT} --src SRC --out {root}`")  # fmt: skip
    split = manifest.splits["train"]
    if split.layout != "scenes":
        options = f" --size {manifest.size}" if manifest.size else ""
        held = manifest.data["splits"].get("validation", {}).get("held_out_from_train")
        if isinstance(held, dict) and held.get("count"):
            options += f" --val-scenes {held['count']}"
        raise UserError(
            f"{root} holds training shards of pre-drawn samples (manifest version {manifest.version}); "
            "training now draws its views from whole scenes: convert the source again with "
            f"`{CONVERT} --src {manifest.source} --out {root}{options}`"
        )
    present = {Path(s).name for s in shards}
    return [SceneRef(str(root / "train" / s.shard), key, frames) for s in split.shards if s.shard in present
            for key, frames in s.scene_frames.items()]  # fmt: skip


def verify_shards(root: str | Path) -> list[str]:
    """Shards whose SHA-256 no longer matches the manifest (or that are missing), as relative paths."""
    root = Path(root)
    manifest = read_manifest(root)
    if manifest is None:
        raise MissingFileError(
            f"no manifest.json in {root}: nothing to verify (convert first: to_shards.py --src SRC --out "
            f"{root})"
        )
    bad = []
    for name, split in manifest.splits.items():
        for shard in split.shards:
            path = root / name / shard.shard
            if not path.exists() or sha256(path) != shard.sha256:
                bad.append(f"{name}/{shard.shard}")
    return bad
