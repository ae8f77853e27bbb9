"""The two layouts of a shard sample and its key: the one definition the converter writes and the streams read.

A sample is the tar members ``KEY.<member>`` of one scene (:func:`safe_key` makes KEY). Training shards
(layout ``scenes``) hold whole scenes: every frame centre-cropped and resized once; the training stream draws
its examples from them at run time (:mod:`aesplat.data.sampler`)::

    KEY.meta.json            {"scene", "dataset", "frames": [source frame ids], "layout": "scene"}
    KEY.extrinsics.npy       float32 [F, 4, 4] camera-to-world in the scene's world frame
    KEY.intrinsics.npy       float32 [F, 3, 3] normalised, for the cropped image
    KEY.frames.offsets.npy   int64 [F + 1]: frame i is bytes offsets[i]:offsets[i + 1] of frames.jpgs
    KEY.frames.jpgs          the frames' JPEGs back to back (last: the loader reads only the frames it picks)

Validation and test shards (layout ``samples``) hold one deterministic sample per scene: the evaluation
index's frames (or :func:`aesplat.data.sampler.evaluation_sample`), plus the extra context frames of the
k-view contexts for k = 2 .. ``eval_context_views`` (:func:`aesplat.data.sampler.evaluation_context`)::

    KEY.meta.json        {"scene", "dataset", "context", "target", "gap", "overlap", "extra", "context_views"}
    KEY.ctx0.jpg … KEY.tgt0.jpg … KEY.xtr0.jpg …   the index's context, its targets, the extra context frames
    KEY.extrinsics.npy / KEY.intrinsics.npy          [V, 4, 4] / [V, 3, 3] in that order
    KEY.tgt0.spec.png …  scenes that carry their specular magnitude only: 8-bit highlight mask per target, 255
                         where the term (cropped like the image, area-resampled) exceeds ``specular_threshold``
"""

from __future__ import annotations

import re

from ..files import name_digest

META = "meta.json"
EXTRINSICS = "extrinsics.npy"
INTRINSICS = "intrinsics.npy"
FRAME_OFFSETS = "frames.offsets.npy"  # layout "scenes"
FRAMES = "frames.jpgs"  # layout "scenes"
SAFE_KEY_LENGTH = 81  # a tar member name (ustar: 100 bytes) holds the key, a dot and the longest extension


def safe_key(text: str) -> str:
    """A WebDataset key: letters, digits, ``-`` and ``_`` (no dots: they separate the extension; no path
    separators), every other character ``_``; a key longer than :data:`SAFE_KEY_LENGTH` keeps its first 72
    characters and gets ``_`` and 8 hex digits of its hash."""
    key = re.sub(r"[^A-Za-z0-9_\-]", "_", text)
    if len(key) <= SAFE_KEY_LENGTH:
        return key
    return f"{key[: SAFE_KEY_LENGTH - 9]}_{name_digest(text)}"


def evaluation_stems(context: int, target: int, extra: int) -> list[str]:
    """The member stems of an evaluation sample's views in the order of its camera rows: ``ctxI`` for its
    ``context`` context frames, ``tgtI`` for its targets, ``xtrI`` for its extra context frames."""
    counts = {"ctx": context, "tgt": target, "xtr": extra}
    return [f"{kind}{i}" for kind, n in counts.items() for i in range(n)]


def image_member(stem: str) -> str:
    return f"{stem}.jpg"


def highlight_member(stem: str) -> str:
    """A target's highlight mask (8-bit PNG, 255 on highlights)."""
    return f"{stem}.spec.png"
