"""Errors a user can cause, and how a command reports them: one line naming the problem and the fix.

A :class:`UserError` is something the person at the keyboard can mend (a missing file, a bad value, a
checkpoint of the wrong kind); the ``aesplat`` entry points print it as ``aesplat COMMAND: message`` on
stderr and exit with status 1 (a malformed command line exits with 2, as argparse does). An ``OSError`` (a
full disk, a read-only or vanished folder, a file without permission) is reported the same way, naming the
file. A command stopped by a signal (SIGTERM, SIGINT, SIGHUP) exits with 128 + the signal's number, so that
``aesplat fit … && aesplat test …`` never mistakes a stopped run for a finished one. Anything else is a bug and
keeps its traceback. ``AESPLAT_DEBUG=1`` shows the traceback of user errors too.
"""

from __future__ import annotations

import errno
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn, TypeVar

DEBUG_ENV = "AESPLAT_DEBUG"
T = TypeVar("T")
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name))
_TAKES_SIGNALS = hasattr(signal, "sigwaitinfo")  # a thread can take signals and see their sender (not macOS)


class UserError(ValueError):
    """A problem with the inputs, stated in one line that names it and the fix (a ValueError, so callers that
    already catch bad values keep doing so)."""


class MissingFileError(UserError, FileNotFoundError):
    """A file or folder the command needs does not exist."""


class RanksLost(RuntimeError):
    """A multi-process run ended because one of its ranks was lost (its node died or stopped answering),
    stated in one line that names the rank and its node."""


class RanksTooSlow(RuntimeError):
    """A multi-process run ended because a collective waited longer than ``--distributed.timeout`` for ranks
    that were alive, stated in one line that names them, where they were, and the fix."""


class Stopped(BaseException):
    """The command was stopped by a signal; it exits with 128 + ``signum``. A BaseException, like
    KeyboardInterrupt, so that no ``except Exception`` on the way swallows it and cleanups still run."""

    def __init__(self, signum: int, message: str = "") -> None:
        self.signum = int(signum)
        self.message = message or f"stopped by {signal_name(signum)}"
        super().__init__(self.message)


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def nearest_existing(path: Path) -> Path:
    """``path`` (resolved) if it exists, else its nearest ancestor that does: where it would be created."""
    probe = path.resolve()
    while not probe.exists():
        probe = probe.parent
    return probe


def check_writable(folder: Path, named: str) -> None:
    """``folder`` is, or can be created inside, a folder this process may write into; else a UserError
    "``named``: cannot write in ..." naming the nearest existing folder."""
    probe = nearest_existing(folder)
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{named}: cannot write in {probe} (no permission)")


def debug() -> bool:
    """Whether ``AESPLAT_DEBUG`` asks for tracebacks of user errors."""
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def fail(command: str, message: str, status: int = 1) -> NoReturn:
    """Stop with ``aesplat COMMAND: message`` on stderr and exit ``status``."""
    if status == 1:
        raise SystemExit(f"aesplat {command}: {message}")  # Python prints it on stderr and exits with 1
    print(f"aesplat {command}: {message}", file=sys.stderr)
    raise SystemExit(status)


# What to do about an OSError, by errno; the others are reported with the system's own words.
_OS_ERROR_HINTS = {
    errno.ENOSPC: "the disk is full: free some space and run the command again",
    errno.EDQUOT: "your disk quota is used up: free some space and run the command again",
    errno.EROFS: "the file system is read-only: give a folder on a writable one",
    errno.EACCES: "no permission: give a path you may read and write, or change its permissions",
    errno.EPERM: "not permitted: give a path you may read and write, or change its permissions",
    errno.ESTALE: "the network file system lost the file (stale handle): run the command again",
    errno.EIO: "the disk or network file system reported an input/output error",
}


def os_error_line(err: OSError) -> str:
    """One line for an OSError: the file, the system's words and, where known, what to do."""
    where = f"{err.filename}: " if err.filename else ""
    if err.filename2:
        where = f"{err.filename} -> {err.filename2}: "
    words = err.strerror or str(err)
    hint = _OS_ERROR_HINTS.get(err.errno or -1)
    return f"{where}{words}" + (f" ({hint})" if hint else "")


def in_this_process_only(handler: Callable[[int, object], None]) -> Callable[[int, object], None]:
    """``handler`` for this process; in a process forked from it later (a worker of a process pool, which
    inherits Python's signal handlers) the signal is ignored: the main process stops its workers itself, and
    a worker that died on a signal sent to the whole process group (Ctrl-C, SLURM) would break the work the
    main process is still waiting for. A data-loader worker needs more: torch sets a SIGTERM handler of its
    own there (:func:`ignore_stop_signals_in_worker`)."""
    pid = os.getpid()

    def only_here(signum: int, frame: object) -> None:
        if os.getpid() == pid:
            handler(signum, frame)

    return only_here


@contextmanager
def stop_signals_blocked() -> Iterator[None]:
    """Block the stop signals in this thread while the block runs: the data-loader workers started meanwhile
    (and every thread they start) begin with them blocked, so that none of their threads takes one before
    :func:`ignore_stop_signals_in_worker` runs there. A stop signal that comes meanwhile waits for the end of
    the block."""
    if not _TAKES_SIGNALS:  # nothing would unblock them in the workers
        yield
        return
    blocked = set(STOP_SIGNALS) - signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)


def ignore_stop_signals_in_worker() -> None:
    """In a data-loader worker (its DataLoader's ``worker_init_fn``): ignore the stop signals, save a SIGTERM
    from the main process, which ends the worker at once.

    A signal sent to the whole process group (``kill -TERM -PGID``, ``timeout``, ``scancel``, a SLURM time
    limit, systemd) reaches the workers too. The main process finishes its step and saves; a worker that died
    of the signal would fail that step ("DataLoader worker ... killed by signal"). The handler a worker
    inherits (:func:`in_this_process_only`) does not last: before the ``worker_init_fn``, torch gives every
    worker a SIGTERM handler of its own, in C, that ends it on a SIGTERM from any process but the main one.
    Nor would ignoring the signals do: the main process ends a worker that does not stop when asked (and, at
    exit, every worker still running) with a SIGTERM of its own, and waits for it. So the signals stay blocked
    (the worker starts with them blocked: :func:`stop_signals_blocked`) and a thread takes them, which tells the
    senders apart as torch's handler does."""
    if not _TAKES_SIGNALS:
        return
    parent = multiprocessing.parent_process()
    main = parent.pid if parent is not None else os.getppid()
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)  # the threads started from here on inherit it
    threading.Thread(target=_take_stop_signals, args=(main,), name="stop-signals", daemon=True).start()


def _take_stop_signals(main: int) -> None:
    """Take the (blocked) stop signals as they come; end the process on a SIGTERM from ``main``."""
    while True:
        info = signal.sigwaitinfo(STOP_SIGNALS)
        if info.si_signo == signal.SIGTERM and info.si_pid == main:
            os._exit(0)  # as torch's own handler does: the worker has nothing to clean up


def heeded_signals() -> list[int]:
    """The stop signals this process does not ignore: ``nohup`` ignores SIGHUP, and a shell starts a
    background job with SIGINT ignored; those stay ignored."""
    return [s for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN]


def _raise_stopped(signum: int, frame: object) -> None:
    if signum == signal.SIGINT:  # as Python does: code that ends on Ctrl-C (a server) catches it
        raise KeyboardInterrupt
    raise Stopped(signum)


@contextmanager
def stopping_on_signals() -> Iterator[None]:
    """SIGTERM and SIGHUP raise :class:`Stopped`, SIGINT KeyboardInterrupt, in this process's main thread
    while the block runs (so ``finally`` blocks and staging cleanups run, where SIGTERM's default would kill
    the process on the spot); processes forked meanwhile ignore them (:func:`in_this_process_only`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = in_this_process_only(_raise_stopped)
    previous = {s: signal.signal(s, handler) for s in heeded_signals()}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def run_reporting_user_errors(command: str, fn: Callable[[], T]) -> T:
    """Call ``fn``; a :class:`UserError` or ``OSError`` becomes one line on stderr and exit status 1 (unless
    debugging); a stop by a signal exits with 128 + its number (one line saying so)."""
    try:
        with stopping_on_signals():
            return fn()
    except (UserError, RanksLost, RanksTooSlow) as err:
        if debug():
            raise
        fail(command, str(err))
    except OSError as err:
        if debug():
            raise
        fail(command, os_error_line(err))
    except Stopped as err:
        fail(command, err.message, 128 + err.signum)
    except KeyboardInterrupt:
        fail(command, "stopped by SIGINT", 128 + signal.SIGINT)
    except SystemExit as err:  # Lightning ends a KeyboardInterrupt with sys.exit(1)
        if err.code == 1 and isinstance(err.__context__, KeyboardInterrupt):
            fail(command, "stopped by SIGINT", 128 + signal.SIGINT)
        raise
