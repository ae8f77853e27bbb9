"""The run's wandb logger, whose failures never stop a fit.

wandb sends every log through a service process of its own (``wandb-core``). When that process ends before
the fit does, each later log raises (``ConnectionResetError: Connection lost``) from inside a training step,
and the fit would stop there without saving. It ends so whenever a signal reaches every process of a job:
``scancel`` or a SLURM time limit sends SIGTERM to the whole job, the service included, so the fit that was
about to save where it stopped lost the run instead. A logger is an observer: here its first failure is one
line on stderr, wandb is shut down (so that its exit hook does not print a traceback), and the fit goes on
without logging; its checkpoints hold the run.
"""

from __future__ import annotations

import sys
from typing import Any

from lightning.pytorch.loggers import WandbLogger


class SteadyWandbLogger(WandbLogger):
    """``WandbLogger`` that stops logging, with one line, at its first failure instead of stopping the fit."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.failure: str | None = None  # why logging stopped; None while it works

    def _steady(self, send, *args: Any, **kwargs: Any) -> Any:
        if self.failure is not None:
            return None
        try:
            return send(*args, **kwargs)
        except Exception as err:  # noqa: BLE001 - any failure of the logger; the fit must go on
            self.failure = f"{type(err).__name__}: {err}"
            print(f"aesplat fit: wandb stopped taking this run's logs ({self.failure}); training goes on "
                  "without them, its checkpoints hold the run", file=sys.stderr)  # fmt: skip
            _shut_down_wandb()
            return None

    def log_metrics(self, *args: Any, **kwargs: Any) -> None:
        self._steady(super().log_metrics, *args, **kwargs)

    def log_hyperparams(self, *args: Any, **kwargs: Any) -> None:
        self._steady(super().log_hyperparams, *args, **kwargs)

    def log_image(self, *args: Any, **kwargs: Any) -> None:
        self._steady(super().log_image, *args, **kwargs)

    def after_save_checkpoint(self, *args: Any, **kwargs: Any) -> None:
        self._steady(super().after_save_checkpoint, *args, **kwargs)

    def finalize(self, *args: Any, **kwargs: Any) -> None:
        self._steady(super().finalize, *args, **kwargs)


def _shut_down_wandb() -> None:
    """Let go of wandb's service after it failed: its teardown unregisters the exit hook that would try again
    (and print a traceback) when the process ends, then fails on the lost connection itself."""
    import wandb

    try:
        wandb.teardown()
    except Exception:  # noqa: BLE001, S110 - the service is gone; what matters is that the hook is unregistered
        pass
