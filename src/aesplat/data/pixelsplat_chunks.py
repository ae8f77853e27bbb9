"""pixelSplat-style ``*.torch`` chunks: the source format RealEstate10K / ACID users have (docs/data.md).

A chunk is a list of scenes ``{url, timestamps int64[F], cameras float32[F, 18], images: list of uint8
tensors holding JPEG bytes, key}``. A camera row is fx, fy, cx, cy (normalised), 0, 0, then the 3x4
world-to-camera matrix row-major. Each split folder holds chunks plus ``index.json`` (key -> chunk file).
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from aesplat.geometry import invert_pose

CAMERA_ROW = 18


def cameras_to_row(extrinsics: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-to-world [F, 4, 4] and normalised intrinsics [F, 3, 3] -> chunk rows float32 [F, 18]."""
    w2c = invert_pose(extrinsics.double())[:, :3, :]  # [F, 3, 4]
    k = intrinsics.double()
    zeros = torch.zeros_like(k[:, 0, :2])
    head = torch.stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]], dim=-1)
    return torch.cat([head, zeros, w2c.reshape(-1, 12)], dim=-1).float()


def row_to_cameras(cameras: Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chunk rows [F, 18] -> (camera-to-world float64 [F, 4, 4], normalised intrinsics float64 [F, 3, 3])."""
    rows = np.asarray(cameras, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != CAMERA_ROW:
        raise ValueError(f"cameras must have shape [F, {CAMERA_ROW}], got {tuple(rows.shape)}")
    f = rows.shape[0]
    k = np.zeros((f, 3, 3))
    k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = (
        rows[:, 0],
        rows[:, 1],
        rows[:, 2],
        rows[:, 3],
        1,
    )
    w2c = np.tile(np.eye(4), (f, 1, 1))
    w2c[:, :3, :] = rows[:, 6:].reshape(f, 3, 4)
    rot_t = np.transpose(w2c[:, :3, :3], (0, 2, 1))
    c2w = np.tile(np.eye(4), (f, 1, 1))
    c2w[:, :3, :3] = rot_t
    c2w[:, :3, 3] = -(rot_t @ w2c[:, :3, 3:])[..., 0]
    return c2w, k


def encode_jpeg(image: np.ndarray, quality: int = 95) -> Tensor:
    """uint8 image [H, W, 3] -> JPEG bytes as a uint8 tensor [N] (the chunk's image field)."""
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=quality)
    return torch.frombuffer(bytearray(buf.getvalue()), dtype=torch.uint8)


def jpeg_bytes(image: Tensor | np.ndarray | bytes) -> bytes:
    """A chunk image entry (uint8 tensor / array of JPEG bytes) -> bytes."""
    if isinstance(image, bytes):
        return image
    if isinstance(image, Tensor):
        image = image.numpy()
    return np.asarray(image, dtype=np.uint8).tobytes()


def write_chunk(scenes: list[dict[str, Any]], path: str | Path) -> None:
    """Save a list of scene dicts as one ``*.torch`` chunk."""
    torch.save(scenes, path)


def load_chunk(path: str | Path) -> list[dict[str, Any]]:
    """Load one chunk (a list of scene dicts). Raises ``ValueError`` naming the file if it is not one."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)  # data files never run code
    except Exception as e:  # noqa: BLE001 - re-raised with the file name
        raise ValueError(f"cannot read chunk {path}: {e}") from e
    if not isinstance(data, list):
        raise ValueError(f"chunk {path} holds {type(data).__name__}, expected a list of scene dicts")
    return data


def write_index(split_dir: str | Path, index: dict[str, str]) -> None:
    """Write ``index.json`` (scene key -> chunk file name) into a split folder."""
    Path(split_dir, "index.json").write_text(json.dumps(index, indent=1, sort_keys=True))


def list_chunks(split_dir: str | Path) -> list[Path]:
    """The chunk files of a split: those named by ``index.json`` if present, else every ``*.torch``, sorted."""
    split_dir = Path(split_dir)
    index_file = split_dir / "index.json"
    if index_file.exists():
        names = sorted(set(json.loads(index_file.read_text()).values()))
        return [split_dir / n for n in names]
    return sorted(split_dir.glob("*.torch"))
