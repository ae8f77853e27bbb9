"""Run directories: one folder per run holds its checkpoints, wandb files, config and evaluation outputs.

The wandb run id is stored in the folder, so a resumed or requeued run continues the same wandb run. Each
``aesplat test`` / ``validate`` writes into a folder of its own inside it (``test-<UTC time>/``, the newest
behind the link ``test-latest``), so an evaluation never changes the training run's files.
"""

from __future__ import annotations

import os
import socket
import uuid
from datetime import datetime, timezone
from pathlib import Path

WANDB_ID_FILE = "wandb_run_id"


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


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """Newest resumable checkpoint of a run: ``checkpoints/last*.ckpt`` or a SLURM ``hpc_ckpt_*.ckpt``."""
    run_dir = Path(run_dir)
    candidates = [*run_dir.glob("checkpoints/last*.ckpt"), *run_dir.glob("hpc_ckpt_*.ckpt")]
    return max(candidates, key=lambda p: p.stat().st_mtime) if candidates else None


def run_artifacts(run_dir: str | Path) -> list[Path]:
    """What marks ``run_dir`` as holding a run (finished or interrupted): its config, wandb id, checkpoints."""
    run_dir = Path(run_dir)
    found = [run_dir / name for name in ("config.yaml", WANDB_ID_FILE) if (run_dir / name).exists()]
    return found + sorted(run_dir.glob("checkpoints/*.ckpt")) + sorted(run_dir.glob("hpc_ckpt_*.ckpt"))


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
