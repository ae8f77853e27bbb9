"""Errors a user can cause, and how a command reports them: one line naming the problem and the fix.

A :class:`UserError` is something the person at the keyboard can mend (a missing file, a bad value, a
checkpoint of the wrong kind); the ``aesplat`` entry points print it as ``aesplat COMMAND: message`` on
stderr and exit with status 1 (a malformed command line exits with 2, as argparse does). Anything else is a
bug and keeps its traceback. ``AESPLAT_DEBUG=1`` shows the traceback of user errors too.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, TypeVar

DEBUG_ENV = "AESPLAT_DEBUG"
T = TypeVar("T")


class UserError(ValueError):
    """A problem with the inputs, stated in one line that names it and the fix (a ValueError, so callers that
    already catch bad values keep doing so)."""


class MissingFileError(UserError, FileNotFoundError):
    """A file or folder the command needs does not exist."""


def check_writable(folder: Path, named: str) -> None:
    """``folder`` is, or can be created inside, a folder this process may write into; else a UserError
    "``named``: cannot write in ..." naming the nearest existing folder."""
    probe = folder.resolve()
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{named}: cannot write in {probe} (no permission)")


def debug() -> bool:
    """Whether ``AESPLAT_DEBUG`` asks for tracebacks of user errors."""
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def fail(command: str, message: str) -> NoReturn:
    """Stop with ``aesplat COMMAND: message`` on stderr and exit status 1."""
    raise SystemExit(f"aesplat {command}: {message}")


def run_reporting_user_errors(command: str, fn: Callable[[], T]) -> T:
    """Call ``fn``; a :class:`UserError` becomes one line on stderr and exit status 1 (unless debugging)."""
    try:
        return fn()
    except UserError as err:
        if debug():
            raise
        fail(command, str(err))
