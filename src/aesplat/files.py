"""Writing and deleting what the user owns, safely, whatever the file system.

- :func:`atomic_write` writes a file whole or not at all: into a temporary file in the destination folder
  (so the final rename never crosses file systems), flushed to the disk (fsync), then renamed over the old
  file, which stays as it was until the new one is complete. A crash, ``kill -9`` or a full disk leaves the
  old file and, at worst, a hidden ``.NAME.*.partial`` file beside it (:func:`remove_partials` clears those).
- :func:`written_whole` writes a file or a folder (a command's ``--out``, an export) the same way: into a
  hidden staging folder beside it, flushed, then renamed into place; a failure leaves the destination as it was.
  Its staging folders name the machine and the process, so that one left by a process killed outright is
  removed by the next write of the same destination (:func:`remove_stale_staging`).
- :func:`check_deletable` is the guard every ``--overwrite`` goes through before it deletes a folder: never
  the file system root, the current folder, the home folder or a folder holding one of them, and never a
  folder holding one of the command's own inputs.
"""

from __future__ import annotations

import glob
import hashlib
import os
import secrets
import shutil
import socket
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import BinaryIO

from .errors import UserError, check_writable

PARTIAL_SUFFIX = ".partial"  # temporary files of atomic_write: .NAME.<random>.partial


def name_digest(name: str) -> str:
    """8 hex digits of ``name``'s SHA-256 (a byte that is not UTF-8 included): appended where a name is
    shortened or has characters replaced for a file or a tar member, so that names stay apart."""
    return hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:8]


def fsync_dir(folder: str | Path) -> None:
    """Flush a folder's entries (a rename into it) to the disk; a no-op where folders cannot be opened."""
    with suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None], mode: int = 0o666) -> Path:
    """Write ``path`` whole or not at all: ``write(f)`` fills a temporary file in the same folder, which is
    fsynced and renamed over ``path``. On any error (a full disk included) or interruption the temporary file
    is removed and ``path`` keeps its previous content; the error is raised naming ``path``. ``mode``: the new
    file's permissions, less the umask (0o600: only its owner may read it)."""
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{path.name}.{secrets.token_hex(4)}{PARTIAL_SUFFIX}"
    # os.open with 0o666 honours the umask, as a plain open() of the final name would (mkstemp would not).
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            try:
                write(f)
            except RuntimeError as err:  # torch's zip writer wraps the OSError of a failed write
                if isinstance(err.__context__, OSError):
                    raise err.__context__ from None
                raise
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with suppress(OSError):
            tmp.unlink()
        if isinstance(err, OSError) and err.filename is None:
            raise OSError(err.errno, err.strerror, str(path)) from None
        raise
    fsync_dir(folder)
    return path


def _fsync_tree(path: Path) -> None:
    """Flush a file, or every file of a folder, to the disk."""
    for file in [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]:
        with open(file, "rb") as f:
            os.fsync(f.fileno())


def _staging_prefix(dest: Path, pid: int | str = "") -> str:
    """Name prefix of the staging folders of ``dest`` made on this machine (by process ``pid``)."""
    return f".{dest.name}.partial-{socket.gethostname()}-{pid}"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_staging(dest: Path) -> list[Path]:
    """The staging folders of ``dest`` left by earlier runs on this machine whose process is gone (killed
    outright, ``kill -9`` or a power loss: a stop signal removes its own); removed, and returned. Another
    machine's (a shared file system) and running processes' are left alone."""
    prefix = _staging_prefix(dest)
    stale = []
    for path in dest.parent.glob(glob.escape(prefix) + "*"):
        pid = path.name[len(prefix) :].split("-", 1)[0]
        if pid.isdigit() and path.is_dir() and not _running(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            stale.append(path)
    return stale


@contextmanager
def written_whole(dest: Path, overwrite: bool, command: str, option: str = "") -> Iterator[Path]:
    """Yield the path to write ``dest`` (a file or a folder) at, inside a staging folder beside it; when the
    block ends without error, what was written there is flushed to the disk and renamed to ``dest`` (an old
    ``dest``, allowed by ``overwrite`` or an empty folder, is replaced as a whole); on error it is deleted and
    ``dest`` untouched. ``command`` and ``option`` (the command and its option that name ``dest``) start the
    messages."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    for path in remove_stale_staging(dest):
        print(f"{command}: removed {path}, the staging folder of an earlier run that was killed")
    staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(dest, os.getpid()) + "-", dir=dest.parent))
    try:
        yield staging / dest.name
        _fsync_tree(staging / dest.name)
        old = None
        if dest.exists():
            if not overwrite and (not dest.is_dir() or any(dest.iterdir())):  # it appeared while we worked
                raise UserError(f"{option} {dest}".strip() + " was filled by something else meanwhile; nothing "
                                "was written")  # fmt: skip
            old = dest.parent / f".{dest.name}.old-{staging.name.rsplit('-', 1)[-1]}"
            os.replace(dest, old)
        os.replace(staging / dest.name, dest)
        fsync_dir(dest.parent)
        if old is not None and old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
        elif old is not None:
            old.unlink()
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def remove_partials(folder: str | Path) -> list[Path]:
    """Remove the temporary files interrupted :func:`atomic_write` calls left in ``folder``; returns them."""
    found = sorted(Path(folder).glob(f".*{PARTIAL_SUFFIX}"))
    for path in found:
        with suppress(FileNotFoundError):
            path.unlink()
    return found


def _forms(path: str | Path) -> set[Path]:
    """A path as written (absolute, normalised) and as it resolves (links followed)."""
    return {Path(os.path.abspath(path)), Path(path).resolve()}


def _holds(folder: str | Path, path: str | Path) -> bool:
    """Whether ``folder`` is or contains ``path``, either as written or with links followed."""
    return any(p == f or f in p.parents for f in _forms(folder) for p in _forms(path))


Inputs = Iterable[tuple[str, "str | Path | None"]]  # (how the command names it, path) of what it reads


def check_deletable(folder: str | Path, flag: str, inputs: Inputs = ()) -> None:
    """Refuse (UserError) to delete ``folder`` when it is or holds the file system root, the current folder,
    the home folder, or one of ``inputs`` (the files and folders the command reads, each with the option
    that names it): as the paths are written, and with symbolic links followed."""
    target = Path(folder).resolve()
    refusal = f"{flag} will not delete {target}: it holds"
    if target == Path(target.anchor) or _holds(folder, Path.cwd()):
        raise UserError(f"{refusal} the current folder; give a folder of its own")
    if _holds(folder, Path.home()):
        raise UserError(f"{refusal} your home folder; give a folder of its own")
    for name, value in inputs:
        if value is None or str(value) == "":
            continue
        if _holds(folder, value):
            raise UserError(
                f"{refusal} {name} {value}, an input of this command; move that input out of it, or give "
                "another folder"
            )


def delete_folder(folder: str | Path, flag: str, inputs: Inputs = (), keep: tuple[str, ...] = ()) -> None:
    """Delete ``folder`` (guarded by :func:`check_deletable`); entries named in ``keep`` stay (the folder
    too, then)."""
    check_deletable(folder, flag, inputs)
    folder = Path(folder)
    if not folder.exists():
        return
    if not keep:
        shutil.rmtree(folder)
        return
    for entry in folder.iterdir():
        if entry.name in keep:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def check_output_dir(out: Path, overwrite: bool, inputs: Inputs = ()) -> None:
    """Refuse, before anything is loaded, an output folder ``--out`` that cannot be written whole: a file, a
    folder that holds something (unless ``overwrite``; and never one that holds the current folder, the home
    folder or one of the command's ``inputs``), or a place without write permission."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a folder; give a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise UserError(
            f"--out {out} is not empty; give a new folder, or --overwrite to replace it (as a whole)"
        )
    if out.is_dir():  # it is replaced as a whole, even empty
        check_deletable(out, "--overwrite" if overwrite else "--out", inputs)
    check_writable(out.resolve().parent, f"--out {out}")  # the folder is renamed into place beside it
