"""Test-only Lightning callbacks, importable by the processes a DDP launch starts."""

import json
from pathlib import Path

from lightning.pytorch import Callback


class RecordTrainingScenes(Callback):
    """Write the training samples each rank saw (scene key + context frames) to ``out_dir/rank<r>.json``."""

    def __init__(self, out_dir: str) -> None:
        self.out_dir = Path(out_dir)
        self.seen: list[list] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        for i, scene in enumerate(batch.scene):
            self.seen.append([scene, batch.context.index[i].tolist()])

    def on_train_end(self, trainer, pl_module) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path = self.out_dir / f"rank{trainer.global_rank}.json"
        path.write_text(json.dumps({"world_size": trainer.world_size, "seen": self.seen}))
