"""The one validation layer of the conversion: every reader's input passes through these checks (docs/data.md).

- :func:`check_scene`: a typed :class:`~aesplat.data.scene.Scene` from any reader (cameras, frames, image sizes,
  field of view, baseline, length); a refusal is a :class:`SceneError` with a reason code and one line.
- :func:`check_rigid`, :func:`inside_folder`: what readers check while parsing (a pose is a rotation and a
  translation; a file a capture names lies inside its scene folder).
- :func:`read_evaluation_index`: an evaluation index file, every entry checked; a malformed one is a
  :class:`~aesplat.errors.UserError` naming the file, the entry and what is wrong.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MissingFileError, UserError
from .scene import Scene, SceneError

RIGID_TOL = 1e-3  # |R^T R - I| and |det R - 1| allowed in a stored pose (text files keep ~7 digits)


def check_rigid(c2w: np.ndarray, what: str) -> None:
    """Raise ``SceneError("bad_pose")`` unless ``c2w`` [4, 4] is finite with a rotation (orthonormal, det 1)
    and a last row (0, 0, 0, 1)."""
    if not np.isfinite(c2w).all():
        raise SceneError("bad_pose", f"{what}: the pose holds NaN or Inf; fix or drop the frame")
    rot = c2w[:3, :3]
    err = max(np.abs(rot.T @ rot - np.eye(3)).max(), abs(np.linalg.det(rot) - 1.0))
    if err > RIGID_TOL or not np.allclose(c2w[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL):
        raise SceneError(
            "bad_pose",
            f"{what}: the pose is not rigid (rotation off by {err:.2g}: scaled or sheared); "
            "store a rotation and a translation only",
        )


def inside_folder(folder: Path, relative: str | Path, what: str, start: Path | None = None) -> Path:
    """``start / relative`` (``start`` defaults to ``folder``), refused (``SceneError("path_outside_scene")``)
    when ``relative`` is absolute or the path climbs out of ``folder`` (``../``): a downloaded capture never
    makes the conversion read another file of the user's. Judged on the names as written (a scene folder may
    itself be a link)."""
    rel = Path(relative)
    joined = Path(os.path.normpath((folder if start is None else start) / rel))
    base = Path(os.path.normpath(folder))
    if rel.is_absolute() or (joined != base and base not in joined.parents):
        raise SceneError(
            "path_outside_scene",
            f"{what}: {relative} lies outside the scene folder {folder}; a capture may only name files "
            "inside its own folder",
        )
    return joined


def check_scene(
    scene: Scene,
    *,
    max_fov_deg: float,
    min_baseline: float,
    expect_shape: tuple[int, int] | None,
    min_frames: int,
    min_frames_why: str,
    min_frames_reason: str = "too_few_frames",
) -> None:
    """Refuse (``SceneError``) a scene the shards cannot be made from.

    Reasons: ``bad_camera`` (arrays that do not match the frames), ``bad_pose``, ``bad_intrinsics``,
    ``duplicate_frames`` (one file listed twice: a context image would also be a target), ``mixed_image_sizes``,
    ``wrong_shape`` (not ``expect_shape`` (H, W)), ``fov_too_wide``, ``degenerate_baseline`` and, below
    ``min_frames`` frames, ``min_frames_reason`` with ``min_frames_why`` saying what needs them."""
    name, frames = scene.key, len(scene)
    if (
        scene.c2w.shape != (frames, 4, 4)
        or scene.intrinsics.shape != (frames, 3, 3)
        or len(scene.sizes) != frames
    ):
        raise SceneError("bad_camera", f"{name}: {frames} frames but cameras of shape {scene.c2w.shape} and "
                         f"{scene.intrinsics.shape}; one camera per frame")  # fmt: skip
    if frames < 3:
        raise SceneError("too_few_frames", f"{name}: {frames} frames; a sample needs at least 3")
    k = scene.intrinsics
    if not np.isfinite(k).all() or (k[:, 0, 0] <= 0).any() or (k[:, 1, 1] <= 0).any():
        raise SceneError("bad_intrinsics", f"{name}: a focal length is not a positive finite number; fix the "
                         "camera")  # fmt: skip
    for i, c2w in enumerate(scene.c2w):
        check_rigid(c2w, f"{name}: frame {scene.names[i] if scene.names else i}")
    if scene.files is not None:  # the same file twice: a context image would also be a target
        seen: dict[str, int] = {}
        for i, file in enumerate(scene.files):
            j = seen.setdefault(os.path.normpath(file), i)
            if j != i:
                shown = scene.names[i] if scene.names else file
                raise SceneError("duplicate_frames", f"{name}: {shown} is listed twice (frames {j} and {i}); "
                                 "drop the duplicate")  # fmt: skip
    sizes = sorted(set(scene.sizes))
    if len(sizes) > 1:
        shown = ", ".join(f"{w}x{h}" for w, h in sizes[:4])
        raise SceneError("mixed_image_sizes", f"{name}: frames of different sizes ({shown}); convert one "
                         "camera per scene (resize or split the capture)")  # fmt: skip
    if expect_shape is not None and (sizes[0][1], sizes[0][0]) != tuple(expect_shape):
        raise SceneError("wrong_shape", f"{name}: images are {sizes[0][0]}x{sizes[0][1]}, --expect-shape "
                         f"says {expect_shape[1]}x{expect_shape[0]}")  # fmt: skip
    fov = np.degrees(2.0 * np.arctan(0.5 / np.stack([k[:, 0, 0], k[:, 1, 1]])))
    if (fov > max_fov_deg).any():
        raise SceneError(
            "fov_too_wide",
            f"{name}: a field of view of {fov.max():.0f} degrees exceeds --max-fov "
            f"{max_fov_deg:g}; raise it if the model should see such views",
        )
    centres = scene.c2w[:, :3, 3]
    if np.linalg.norm(centres.max(0) - centres.min(0)) < min_baseline:
        raise SceneError("degenerate_baseline", f"{name}: the cameras move less than --min-baseline "
                         f"{min_baseline:g}; a static capture cannot be used")  # fmt: skip
    if frames < min_frames:
        raise SceneError(min_frames_reason, f"{name}: {frames} frames, {min_frames_why} needs {min_frames}")


# ------------------------------------------------------------------------------------------- evaluation index


@dataclass(frozen=True)
class EvaluationEntry:
    """One scene's evaluation sample: context frame indices (at least two, view 0 first), target indices and
    the context views' overlap (None where unknown). Frames count in the scene's frame order."""

    context: tuple[int, ...]
    target: tuple[int, ...]
    overlap: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"context": list(self.context), "target": list(self.target), "overlap": self.overlap}


def _frames(value: Any, field_name: str, least: int) -> tuple[int, ...] | str:
    """A list of at least ``least`` distinct frame indices >= 0, or what is wrong with it."""
    if not isinstance(value, list) or len(value) < least:
        return f"`{field_name}` must be a list of at least {least} frame indices, got {value!r}"
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return f"`{field_name}` must hold whole numbers, got {value!r}"
    if min(value) < 0:
        return f"`{field_name}` holds a negative frame index ({min(value)}); frames count from 0"
    if len(set(value)) != len(value):
        return f"`{field_name}` lists a frame twice: {value}"
    return tuple(value)


def parse_evaluation_entry(key: str, entry: Any, what: str) -> EvaluationEntry | None:
    """One index entry (``null`` or ``{"context", "target", "overlap"}``) checked; malformed: ``UserError``."""
    if entry is None:
        return None
    if not isinstance(entry, dict):
        raise UserError(
            f"{what}: entry {key!r} must be null or an object with context and target, got {entry!r}"
        )
    context = _frames(entry.get("context"), "context", 2)
    target = _frames(entry.get("target"), "target", 1)
    for problem in (context, target):
        if isinstance(problem, str):
            raise UserError(f"{what}: entry {key!r}: {problem}")
    overlap = entry.get("overlap")
    if overlap is not None and (isinstance(overlap, bool) or not isinstance(overlap, (int, float))):
        raise UserError(f"{what}: entry {key!r}: `overlap` must be a number or null, got {overlap!r}")
    return EvaluationEntry(context, target, None if overlap is None or not math.isfinite(overlap) else overlap)


def read_evaluation_index(path: str | Path) -> dict[str, EvaluationEntry | None]:
    """An evaluation index JSON ``{scene: null | {"context": [i, j, ...], "target": [...], "overlap": x}}``,
    every entry checked: at least two context and one target frame, whole numbers >= 0, none repeated within
    a list. A frame may be both a context and a target view, as in the literature's indices (pixelSplat's and
    NAS3R's RealEstate10K index has such entries), so that they are read as they are. A missing or malformed
    file is one ``UserError`` line."""
    path = Path(path)
    what = f"evaluation index {path}"
    if not path.is_file():
        raise MissingFileError(f"{what} does not exist")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UserError(f"{what} is not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise UserError(f"{what} must hold an object {{scene: entry}}, got {type(data).__name__}")
    return {str(key): parse_evaluation_entry(str(key), entry, what) for key, entry in data.items()}
