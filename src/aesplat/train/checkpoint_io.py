"""How a run writes and reads its checkpoint files: whole or not at all, and safely.

Lightning's own writer stages a checkpoint in ``$TMPDIR`` and moves it into place; when the run folder is on
another file system (local ``/tmp``, the run on NFS or Lustre: the usual cluster layout) the move is a copy
that truncates the previous ``last.ckpt`` first, so ``kill -9`` or a full disk during a save leaves a
truncated file and nothing to resume from. :class:`AtomicCheckpointIO` writes into the destination folder
(``aesplat.files.atomic_write``: temporary file, fsync, rename), so the previous checkpoint stays whole until
the new one is, and it reads through the project's safe loader, so resuming never unpickles a class.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from lightning.fabric.utilities.types import _PATH
from lightning.pytorch.plugins.io import TorchCheckpointIO

from aesplat.files import atomic_write
from aesplat.model.weights import read_torch_file


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` with atomic writes in the destination folder and safe, memory-mapped reads."""

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: _PATH, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options, got {storage_options!r}")
        atomic_write(Path(path), lambda f: torch.save(checkpoint, f))

    def load_checkpoint(
        self, path: _PATH, map_location: Any | None = None, weights_only: bool | None = None
    ) -> dict:
        checkpoint = read_torch_file(path, "checkpoint")  # tensors and plain containers only, whatever asked
        if not isinstance(checkpoint, dict):
            raise ValueError(f"checkpoint file {path} holds no Lightning checkpoint")
        return checkpoint
