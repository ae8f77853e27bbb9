"""The export formats, by name, and one call that writes any of them beside a prediction.

    EXPORTS = {"colmap": ..., "nerfstudio": ..., "splat": ...}
    export_prediction(PREDICT_DIR, ["colmap", "splat"])   # PREDICT_DIR/colmap/, PREDICT_DIR/gaussians.splat

Each output is written whole (``aesplat.files.written_whole``: a staging folder beside it, flushed to disk,
then renamed into place), so a crash or a full disk leaves either the complete output or none. Destinations
that exist are refused (before anything is written) unless ``overwrite``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..errors import UserError
from ..files import written_whole
from .colmap import write_colmap
from .nerfstudio import write_nerfstudio
from .prediction import PredictedScene, read_prediction
from .splat import write_splat


@dataclass(frozen=True)
class ExportFormat:
    """One export: where it goes in the prediction folder, and the function that writes it there."""

    dest: str  # a folder (colmap/) or a file (gaussians.splat) inside the prediction folder
    write: Callable[[PredictedScene, Path], object]
    description: str


EXPORTS: dict[str, ExportFormat] = {
    "colmap": ExportFormat("colmap", write_colmap, "COLMAP text model (sparse/0) and images"),
    "nerfstudio": ExportFormat("nerfstudio", write_nerfstudio, "nerfstudio transforms.json and images"),
    "splat": ExportFormat("gaussians.splat", lambda s, p: write_splat(p, s.gaussians), "web-viewer .splat"),
}


def parse_formats(text: str) -> list[str]:
    """``"colmap,splat"`` -> ["colmap", "splat"]; an unknown name is a UserError listing the known ones."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in EXPORTS]
    if unknown or not names:
        raise UserError(f"unknown export format {unknown[0] if unknown else text!r}; choose from "
                        f"{', '.join(EXPORTS)} (comma-separated)")  # fmt: skip
    return list(dict.fromkeys(names))


def export_prediction(
    folder: str | Path, formats: list[str], *, overwrite: bool = False, scene: PredictedScene | None = None
) -> list[Path]:
    """Write ``formats`` (names of ``EXPORTS``) into the prediction folder ``folder``; returns their paths.

    scene: the folder already read (``read_prediction``), to save reading it again.
    """
    if not formats:  # nothing asked: the prediction is not read back
        return []
    folder = Path(folder)
    for name in formats:
        if name not in EXPORTS:
            raise UserError(f"unknown export format {name!r}; choose from {', '.join(EXPORTS)}")
    scene = scene or read_prediction(folder)
    dests = [folder / EXPORTS[name].dest for name in formats]
    if not overwrite and (existing := [d for d in dests if d.exists()]):
        raise UserError(f"{existing[0]} exists; remove it, or give --overwrite to replace it")
    for name, dest in zip(formats, dests):
        with written_whole(dest, overwrite, "aesplat export") as path:
            EXPORTS[name].write(scene, path)
    return dests
