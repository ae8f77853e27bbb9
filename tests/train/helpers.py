"""Test-only Lightning callbacks, importable by the processes a DDP launch starts."""

import json
import os
from pathlib import Path

from lightning.pytorch import Callback


class RecordTrainingScenes(Callback):
    """Write the training samples each rank saw (scene key + context frames) to ``out_dir/rank<r>.json``,
    with how the rank was launched (cluster environment, parent process, SLURM task id and restart count)."""

    def __init__(self, out_dir: str) -> None:
        self.out_dir = Path(out_dir)
        self.seen: list[list] = []
        self.first_step: int | None = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        if self.first_step is None:
            self.first_step = trainer.global_step
        for i, scene in enumerate(batch.scene):
            self.seen.append([scene, batch.context.index[i].tolist()])

    def on_train_end(self, trainer, pl_module) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path = self.out_dir / f"rank{trainer.global_rank}.json"
        environment = getattr(trainer.strategy, "cluster_environment", None)
        parent = Path(f"/proc/{os.getppid()}/comm")
        record = {
            "world_size": trainer.world_size, "seen": self.seen, "first_step": self.first_step,
            "cluster_environment": type(environment).__name__,
            "processes_started_outside": getattr(environment, "creates_processes_externally", False),
            "parent_process": parent.read_text().strip() if parent.exists() else None,
            "slurm_procid": os.environ.get("SLURM_PROCID"),
            "slurm_restart_count": os.environ.get("SLURM_RESTART_COUNT", "0"),
        }  # fmt: skip
        path.write_text(json.dumps(record))


class HoldUntilRequeueSignal(Callback):
    """Before training step ``at`` (global step), wait until the SLURM requeue signal is pending (``aesplat
    fit`` holds it blocked), at most ``timeout`` seconds; in the first run of the job only (a requeued job
    trains on).

    It keeps a job that is to be preempted running until the test has signalled it, whatever the machine's
    speed, so the requeue cannot lose a race with the end of the job; it changes nothing in the training."""

    def __init__(self, at: int, timeout: float = 300.0) -> None:
        self.at, self.timeout = at, timeout

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        import signal
        import time

        if trainer.global_step != self.at or os.environ.get("SLURM_RESTART_COUNT", "0") != "0":
            return
        deadline = time.monotonic() + self.timeout
        while signal.SIGUSR1 not in signal.sigpending() and time.monotonic() < deadline:
            time.sleep(0.05)
