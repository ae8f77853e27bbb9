"""The run's wandb logger: its first failure is one line and the end of logging, never the end of the fit
(the process-level case, wandb's service ended by a job's SIGTERM: tests/test_cli_robust.py)."""

import pytest

pytest.importorskip("wandb")

from lightning.pytorch.loggers import WandbLogger  # noqa: E402

from aesplat.train.logger import SteadyWandbLogger  # noqa: E402


def test_the_first_failure_is_one_line_and_later_logs_are_not_sent(tmp_path, monkeypatch, capsys):
    sent, torn_down = [], []

    def lost(self, *args, **kwargs):
        sent.append(args)
        raise ConnectionResetError("Connection lost")

    monkeypatch.setattr(WandbLogger, "log_metrics", lost)
    monkeypatch.setattr(WandbLogger, "log_image", lambda self, *a, **k: sent.append(a))
    monkeypatch.setattr("wandb.teardown", lambda *a, **k: torn_down.append(True))
    logger = SteadyWandbLogger(save_dir=str(tmp_path), offline=True, mode="disabled")
    logger.log_metrics({"train/loss": 1.0}, step=1)
    logger.log_metrics({"train/loss": 0.5}, step=2)
    logger.log_image(key="train/images", images=[])
    assert len(sent) == 1 and torn_down == [True]
    assert logger.failure == "ConnectionResetError: Connection lost"
    assert capsys.readouterr().err.splitlines() == [
        "aesplat fit: wandb stopped taking this run's logs (ConnectionResetError: Connection lost); training "
        "goes on without them, its checkpoints hold the run"
    ]


def test_logs_pass_through_while_wandb_works(tmp_path, monkeypatch, capsys):
    sent = []
    monkeypatch.setattr(WandbLogger, "log_metrics", lambda self, m, step=None: sent.append((m, step)))
    logger = SteadyWandbLogger(save_dir=str(tmp_path), offline=True, mode="disabled")
    logger.log_metrics({"train/loss": 1.0}, step=3)
    assert sent == [({"train/loss": 1.0}, 3)] and logger.failure is None and capsys.readouterr().err == ""
