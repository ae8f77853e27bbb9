"""What the argparse commands (``aesplat predict``, ``aesplat bench``) share: a parser whose errors are one
line, help that shows defaults, and the ``--device`` option."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

import torch

from .errors import UserError, debug


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except None / False ones (their help says what happens instead)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


class OneLineParser(argparse.ArgumentParser):
    """A malformed command line is one line (what is wrong, and where the options are listed), exit 2."""

    def error(self, message: str) -> NoReturn:
        if debug():
            super().error(message)
        print(f"{self.prog}: {message} (`{self.prog} --help` lists the options)", file=sys.stderr)
        raise SystemExit(2)


def resolve_device(name: str, flag: str = "--device") -> torch.device:
    """``auto`` -> cuda when available, else cpu; anything else as given, checked (UserError if unknown or
    not here)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise UserError(f"{flag} {name} is not a device: give cpu, cuda, cuda:1, ... or auto") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"{flag} {name} asked for CUDA, which is not available here")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise UserError(f"{flag} {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif device.type != "cpu":
        raise UserError(f"{flag} {name}: only cpu and cuda devices are supported")
    return device
