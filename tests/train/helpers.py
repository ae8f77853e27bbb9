"""What the training tests share: the smoke config's module, data and trainer, a run folder locked by another
process, and test-only Lightning callbacks (importable by the processes a DDP or SLURM launch starts)."""

import json
import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path

import lightning as L
from lightning.pytorch import Callback
from omegaconf import OmegaConf

from aesplat.data import DataModule
from aesplat.train import AESplatModule
from aesplat.train.run_dir import lock_run
from aesplat.train.signals import REQUEUE_SIGNAL, SignalsAtStepBoundary
from tests.helpers import REPO

SMOKE = REPO / "conf" / "smoke.yaml"


def smoke_config() -> dict:
    return OmegaConf.to_container(OmegaConf.load(SMOKE), resolve=True)


def make_module(**overrides) -> AESplatModule:
    model = smoke_config()["model"]
    for key, value in overrides.items():
        model[key] = {**model.get(key, {}), **value} if isinstance(value, dict) else value
    return AESplatModule(**model)


def make_data(root, **overrides) -> DataModule:
    return DataModule(**{**smoke_config()["data"], "root": str(root), **overrides})


def make_trainer(max_steps: int, tmp_path, callbacks=(), **kwargs) -> L.Trainer:
    return L.Trainer(accelerator="cpu", devices=1, max_steps=max_steps, logger=False, callbacks=list(callbacks),
                     enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                     limit_val_batches=0, default_root_dir=str(tmp_path), **kwargs)  # fmt: skip


def hold_lock(run: Path):
    """A forked process that holds ``run``'s lock until the returned connection is closed (fork: no imports)."""
    context = multiprocessing.get_context("fork")
    here, there = context.Pipe()

    def hold(conn) -> None:
        lock_run(run)
        conn.send("locked")
        conn.poll(120)  # until the test says it is done (or two minutes)

    process = context.Process(target=hold, args=(there,), daemon=True)
    process.start()
    assert here.recv() == "locked"
    return process, here


class RecordTrainingScenes(Callback):
    """Write the training samples each rank saw (scene key + context frames) and the loss of each of its steps
    to ``out_dir/rank<r>.json``, with how the rank was launched (cluster environment, parent process, SLURM
    task id, node and restart count)."""

    def __init__(self, out_dir: str) -> None:
        self.out_dir = Path(out_dir)
        self.seen: list[list] = []
        self.losses: list[float] = []
        self.first_step: int | None = None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        self.losses.append(float(loss))

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
            "world_size": trainer.world_size, "seen": self.seen, "losses": self.losses,
            "first_step": self.first_step, "node": os.environ.get("SLURMD_NODENAME"),
            "node_rank": trainer.node_rank,
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
        if trainer.global_step != self.at or os.environ.get("SLURM_RESTART_COUNT", "0") != "0":
            return
        deadline = time.monotonic() + self.timeout
        while signal.SIGUSR1 not in signal.sigpending() and time.monotonic() < deadline:
            time.sleep(0.05)


class SignalDuringStep(Callback):
    """Send ``signum`` (the requeue signal unless given) to the main thread at the start of training batch
    ``at`` (mid-step), and with ``again`` a second time at the end of that step; ``steps_after``: the global
    steps of the batches that started after it."""

    def __init__(self, at: int, signum: int = REQUEUE_SIGNAL, again: bool = False) -> None:
        self.at, self.signum, self.again = at, signum, again
        self.steps_after: list[int] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if batch_idx == self.at:
            signal.pthread_kill(threading.main_thread().ident, self.signum)
        elif batch_idx > self.at:
            self.steps_after.append(trainer.global_step)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if batch_idx == self.at and self.again:
            signal.pthread_kill(threading.main_thread().ident, self.signum)


class HoldUntilFile(Callback):
    """Before training step ``at`` (global step), in the first run of a job only, write ``<ready>.rank<r>``
    (this process's pid, its parent's and its node) and wait until the file ``go`` exists, at most ``timeout``
    seconds: a test can take a node away while every rank is between steps, then let the others go on."""

    def __init__(self, ready: str, go: str, at: int, timeout: float = 300.0) -> None:
        self.ready, self.go, self.at, self.timeout = ready, Path(go), at, timeout

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        if trainer.global_step != self.at or os.environ.get("SLURM_RESTART_COUNT", "0") != "0":
            return
        mine = {"pid": os.getpid(), "parent": os.getppid(), "node": os.environ.get("SLURMD_NODENAME")}
        Path(f"{self.ready}.rank{trainer.global_rank}").write_text(json.dumps(mine))
        deadline = time.monotonic() + self.timeout
        while not self.go.exists() and time.monotonic() < deadline:
            time.sleep(0.05)


class HoldUntilStopSignal(Callback):
    """At the start of training batch ``at`` (with ``validation``: of validation batch ``at``), write the file
    ``ready`` and wait until the fit has a stop signal, at most ``timeout`` seconds. A test that signals the
    process (or its whole process group, data-loader workers included) once ``ready`` is there knows that
    training runs, and that the signal comes during that step; the training itself is unchanged."""

    def __init__(self, ready: str, at: int = 1, validation: bool = False, timeout: float = 300.0) -> None:
        self.ready, self.at, self.validation, self.timeout = Path(ready), at, validation, timeout

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if not self.validation and batch_idx == self.at:
            self._hold(trainer)

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
        if self.validation and batch_idx == self.at and not trainer.sanity_checking:
            self._hold(trainer)

    def _hold(self, trainer) -> None:
        signals = next(c for c in trainer.callbacks if isinstance(c, SignalsAtStepBoundary))
        self.ready.write_text(f"{os.getpid()}\n")
        deadline = time.monotonic() + self.timeout
        while signals.stop_signal is None and time.monotonic() < deadline:
            time.sleep(0.05)  # the stop signal's handler runs here, in the main thread


class SlowRank(Callback):
    """Global rank ``rank`` sleeps ``seconds`` before training batch ``at``, as a rank whose first batch comes
    from a cold data cache would wait: slow, not lost (its heartbeat goes on)."""

    def __init__(self, rank: int, seconds: float, at: int = 0) -> None:
        self.rank, self.seconds, self.at = rank, seconds, at

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        if trainer.global_rank == self.rank and batch_idx == self.at:
            time.sleep(self.seconds)


class SlowToStart(Callback):
    """In the rank Lightning starts as local rank ``rank`` (``LOCAL_RANK``), sleep ``seconds`` when the command
    builds its callbacks: before that rank writes anything or joins the process group, as a rank that imports
    from a slow file system would start."""

    def __init__(self, rank: int, seconds: float) -> None:
        if os.environ.get("LOCAL_RANK") == str(rank):
            time.sleep(seconds)
