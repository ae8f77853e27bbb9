"""What the commands share: a parser whose errors are one line, help that shows defaults, and the ``--device``
option."""

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
    """A malformed command line is one line (what is wrong, and where the options are listed), exit 2: the
    parser of `aesplat predict` and `aesplat bench`, and mixed into Lightning's for `aesplat fit|validate|test`.
    ``AESPLAT_DEBUG=1``, or a parser told not to exit on errors: the parser's own error."""

    def command(self) -> str:
        """The command the error line names."""
        return self.prog

    def error_line(self, message: str) -> str:
        """What is wrong, in one line."""
        return message

    def error(self, message: str, *args) -> NoReturn:
        if debug() or not self.exit_on_error:
            super().error(message, *args)
        command = self.command()
        print(f"{command}: {self.error_line(message)} (`{command} --help` lists the options)", file=sys.stderr)
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
