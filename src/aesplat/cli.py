"""The `aesplat` command: `aesplat NAME …` runs the ``main`` of the module ``COMMANDS`` names for NAME,
imported only then (a command does not wait for the others' imports); `aesplat fit|validate|test` is the
LightningCLI of ``aesplat.lightning_cli``. A user's error is one line (``aesplat.errors``).
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
from collections.abc import Sequence

from aesplat.errors import run_reporting_user_errors

# name -> (the module whose ``main(argv)`` runs it, what it does: its line of `aesplat --help`)
COMMANDS = {
    "predict": ("aesplat.predict", "images -> Gaussians, cameras, renders"),
    "bench": ("aesplat.bench.command", "accuracy-versus-time report"),
    "export": ("aesplat.export.command", "a prediction for COLMAP, nerfstudio, web viewers"),
    "view": ("aesplat.view.command", "a prediction in the browser"),
}
LIGHTNING_COMMANDS = ("fit", "validate", "test")


def hold_requeue_signal() -> bool:
    """Inside a SLURM job, block SIGUSR1 (the requeue signal) in this thread; True if it did so.

    Called before torch is imported (which starts a thread): every thread and process started afterwards
    inherits the mask, so the signal waits, pending, for ``aesplat.train.signals.SignalsAtStepBoundary``.
    """
    if sys.platform == "win32" or "SLURM_JOB_ID" not in os.environ:
        return False
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})
    return True


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the `aesplat` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["fit"]:
        hold_requeue_signal()
    if argv in ([], ["-h"], ["--help"]):
        print("aesplat fit|validate|test -c CONFIG.yaml [--key value ...]  train / evaluate (LightningCLI)")
        for name, (_, summary) in COMMANDS.items():
            print(f"{f'aesplat {name} --help':<42}{summary}")
        print()
        argv = ["--help"]
    known = argv[:1] and argv[0] in (*COMMANDS, *LIGHTNING_COMMANDS)
    command = argv[0] if known else "fit|validate|test"
    # A UserError is the user's to mend: one line; anything else is a bug and keeps its traceback.
    run_reporting_user_errors(command, lambda: _run_command(command, argv))


def _run_command(command: str, argv: list[str]) -> None:
    if command in COMMANDS:
        importlib.import_module(COMMANDS[command][0]).main(argv[1:])
    else:
        from aesplat.lightning_cli import run_lightning

        run_lightning(argv)


if __name__ == "__main__":
    main()
