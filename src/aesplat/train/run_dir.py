"""Run directories: one folder per run holds its checkpoints, wandb files, config and evaluation outputs.

The wandb run id is stored in the folder, so a resumed or requeued run continues the same wandb run. Each
``aesplat test`` / ``validate`` writes into a folder of its own inside it (``test-<UTC time>/``, the newest
behind the link ``test-latest``), so an evaluation never changes the training run's files. One ``aesplat fit``
at a time trains in a run folder (:func:`lock_run`), and a fit that stops before its first checkpoint takes
back its run markers (:class:`FitWrites`), so the corrected command is not refused as "already holds a run".
"""

from __future__ import annotations

import fcntl
import os
import socket
import sys
import uuid
from contextlib import suppress
from datetime import datetime, timezone
from pathlib import Path

from aesplat.errors import UserError
from aesplat.files import remove_partials

WANDB_ID_FILE = "wandb_run_id"
LOCK_FILE = ".lock"  # held by the `aesplat fit` training in the folder (pid, host and start time inside)


def wandb_run_id(run_dir: str | Path) -> str:
    """The wandb run id of ``run_dir``: read from ``run_dir/wandb_run_id``, created once if absent.

    Creation is atomic (hard link of a temporary file), so ranks or requeued jobs racing on a shared file
    system all end up with the same id.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / WANDB_ID_FILE
    if not path.exists():
        tmp = run_dir / f".{WANDB_ID_FILE}.{os.getpid()}.{uuid.uuid4().hex[:6]}"
        tmp.write_text(uuid.uuid4().hex[:12] + "\n")
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
        finally:
            tmp.unlink()
    return path.read_text().strip()


def wandb_mode(requested: str = "auto", host: str = "api.wandb.ai", timeout: float = 1.5) -> str:
    """Resolve the wandb mode: ``WANDB_MODE`` wins; ``auto`` is online only when wandb's server is reachable."""
    env = os.environ.get("WANDB_MODE")
    if env:
        return "disabled" if env == "dryrun" else env
    if requested != "auto":
        return requested
    try:
        socket.create_connection((host, 443), timeout=timeout).close()
        return "online"
    except OSError:
        return "offline"


def run_checkpoint_files(run_dir: str | Path) -> list[Path]:
    """The checkpoint files of a run: ``checkpoints/*.ckpt`` and SLURM's ``hpc_ckpt_*.ckpt``."""
    run_dir = Path(run_dir)
    return sorted(run_dir.glob("checkpoints/*.ckpt")) + sorted(run_dir.glob("hpc_ckpt_*.ckpt"))


def run_artifacts(run_dir: str | Path) -> list[Path]:
    """What marks ``run_dir`` as holding a run (finished or interrupted): its config, wandb id, checkpoints."""
    run_dir = Path(run_dir)
    found = [run_dir / name for name in ("config.yaml", WANDB_ID_FILE) if (run_dir / name).exists()]
    return found + run_checkpoint_files(run_dir)


_held_locks: dict[Path, int] = {}  # run folder -> open descriptor of its lock file, for the process's life


def lock_run(run_dir: str | Path) -> None:
    """Make this process the one ``aesplat fit`` training in ``run_dir`` until it exits (a POSIX lock on
    ``run_dir/.lock``, which network file systems honour across machines); UserError naming the holder if
    another process has it. Creates ``run_dir``."""
    run_dir = Path(run_dir).resolve()
    if run_dir in _held_locks:
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise UserError(
            f"{run_dir} is in use: {holder} is training there; wait for it to end, or give another "
            "--trainer.default_root_dir"
        ) from None
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"aesplat fit (pid {os.getpid()} on {socket.gethostname()}, since {stamp})\n".encode(), 0)
    _held_locks[run_dir] = fd


def unlock_run(run_dir: str | Path) -> None:
    """Let go of ``run_dir``'s lock (it also goes when the process ends)."""
    fd = _held_locks.pop(Path(run_dir).resolve(), None)
    if fd is not None:
        os.close(fd)


class FitWrites:
    """What one ``aesplat fit`` adds to its run folder that would mark the folder as holding a run, so that a
    fit that fails or stops before its first checkpoint can take it back and the corrected command is not
    refused: whether the folder existed is noted when this is made, its entries when the fit is about to
    write (:meth:`snapshot`). What a failure leaves to read (wandb logs, a non-finite step's report) stays."""

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.existed = self.run_dir.exists()
        self.before: set[str] = set()
        self.snapshot()

    def snapshot(self) -> None:
        """Note what the run folder holds now: :meth:`discard_if_untrained` leaves it."""
        self.before = {p.name for p in self.run_dir.iterdir()} if self.run_dir.is_dir() else set()

    def discard_if_untrained(self) -> list[str]:
        """When the run holds no checkpoint, remove the run markers this fit wrote (``config.yaml``, the wandb
        id, an empty ``checkpoints/``), and the folder itself if this fit made it and nothing else is in it;
        returns the names removed."""
        checkpoints = self.run_dir / "checkpoints"
        remove_partials(checkpoints)
        if not self.run_dir.is_dir() or run_checkpoint_files(self.run_dir):
            return []
        removed = []
        for name in ("config.yaml", WANDB_ID_FILE):
            if name not in self.before and (self.run_dir / name).is_file():
                (self.run_dir / name).unlink()
                removed.append(name)
        if "checkpoints" not in self.before and checkpoints.is_dir() and not any(checkpoints.iterdir()):
            checkpoints.rmdir()
        if not self.existed and {p.name for p in self.run_dir.iterdir()} <= {LOCK_FILE}:
            unlock_run(self.run_dir)
            with suppress(FileNotFoundError):
                (self.run_dir / LOCK_FILE).unlink()
            with suppress(OSError):
                self.run_dir.rmdir()
        if removed:
            print(f"aesplat fit: nothing was trained: removed {', '.join(removed)} from {self.run_dir}, so the "
                  "corrected command can start there", file=sys.stderr)  # fmt: skip
        return removed


def evaluation_dir(base: str | Path, command: str, now: datetime | None = None) -> Path:
    """A new folder for one ``aesplat test`` / ``validate``: ``base/<command>-<UTC time>`` (``-2``, ``-3``...
    when that name is taken). Under SLURM the job id replaces the time, so every task of the job agrees."""
    base = Path(base)
    job = os.environ.get("SLURM_JOB_ID")
    stamp = f"job{job}" if job else (now or datetime.now(timezone.utc)).strftime("%Y%m%d-%H%M%S")
    folder, n = base / f"{command}-{stamp}", 1
    while folder.exists() and not job:
        n += 1
        folder = base / f"{command}-{stamp}-{n}"
    return folder


def point_latest(folder: str | Path) -> Path:
    """Make ``<parent>/<command>-latest`` a relative link to ``folder`` (replaced atomically); returns it."""
    folder = Path(folder)
    link = folder.parent / f"{folder.name.split('-', 1)[0]}-latest"
    tmp = folder.parent / f".{link.name}.{os.getpid()}"
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(folder.name, target_is_directory=True)
    os.replace(tmp, link)
    return link
