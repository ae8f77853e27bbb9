"""``manifest.json``: what a shard folder holds, read as a typed record (docs/data.md).

The manifest's ``version`` says which layout the folder holds: 1, pre-drawn samples in every split (written
before training drew its views from whole scenes); 2, whole scenes in ``train`` (layout ``scenes``) and
deterministic samples in ``validation`` / ``test`` (layout ``samples``). Every reader of a shard folder
(:func:`find_shards`, :func:`has_split`, :func:`training_scenes`, :func:`verify_shards`) goes through
:func:`read_manifest`, so a damaged manifest, an old layout or a folder of tars that are not shards is one
line naming the fix, never a traceback or an empty run.
"""

from __future__ import annotations

import hashlib
import json
import logging
import tarfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import MissingFileError, UserError

MANIFEST_VERSION = 2
LAYOUTS = ("scenes", "samples")
CONVERT = "python data_prep/to_shards.py"

log = logging.getLogger("aesplat.data")


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class ShardRecord:
    """One shard of a split: its file name, checksum, and (training shards) its scenes' frame counts."""

    shard: str
    sha256: str | None
    samples: int = 0
    scene_frames: dict[str, int] = field(default_factory=dict)


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


def _split(path: Path, name: str, entry: Any, version: int) -> SplitRecord:
    if not isinstance(entry, dict) or not isinstance(entry.get("shards"), list):
        raise _damaged(path, f"split {name!r} has no list of shards")
    layout = entry.get("layout", "samples") if version >= 2 else "samples"
    if layout not in LAYOUTS:
        raise _damaged(path, f"split {name!r} has an unknown layout {layout!r}")
    shards = []
    for item in entry["shards"]:
        if not isinstance(item, dict) or not isinstance(item.get("shard"), str):
            raise _damaged(path, f"split {name!r} lists a shard without a file name")
        frames = item.get("scene_frames") or {}
        if not isinstance(frames, dict) or not all(isinstance(v, int) for v in frames.values()):
            raise _damaged(path, f"split {name!r}: shard {item['shard']} has malformed scene_frames")
        shards.append(ShardRecord(item["shard"], item.get("sha256"), int(item.get("samples", 0)), frames))
    samples = entry.get("evaluation_samples") if version >= 2 else None
    targets: dict[int, int] = {}
    for sample in samples.values() if isinstance(samples, dict) else ():
        if not isinstance(sample, dict) or not isinstance(sample.get("target"), list):
            raise _damaged(path, f"split {name!r} lists an evaluation sample without targets")
        targets[len(sample["target"])] = targets.get(len(sample["target"]), 0) + 1
    return SplitRecord(layout, shards, int(entry.get("context_views", 2)) if version >= 2 else 2, targets)


def read_manifest(root: str | Path) -> Manifest | None:
    """``root/manifest.json`` as a :class:`Manifest`; None when there is none; a ``UserError`` when it is
    unreadable or malformed."""
    path = Path(root) / "manifest.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _damaged(path, f"not valid JSON: {err}") from None
    if not isinstance(data, dict) or not isinstance(data.get("splits"), dict):
        raise _damaged(path, "no `splits` object")
    version = data.get("version", 1)
    if not isinstance(version, int) or not 1 <= version <= MANIFEST_VERSION:
        raise UserError(f"{path} has version {version!r}; this aesplat reads versions 1 to {MANIFEST_VERSION}: "
                        "update aesplat or convert the source again")  # fmt: skip
    splits = {name: _split(path, name, entry, version) for name, entry in data["splits"].items()}
    return Manifest(version, str(data.get("source", "SRC")), splits, data)


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
