"""The `aesplat` command.

    aesplat fit|validate|test -c conf/FILE.yaml [-c conf/OVERLAY.yaml …] [--dotted.key value …]
    aesplat predict …     (aesplat.predict)
    aesplat bench …       (aesplat.tradeoffs)

fit/validate/test are a LightningCLI in OmegaConf parser mode (``${…}`` interpolation inside a file, several
``-c`` files layered left to right, ``--print_config`` to see the result). Besides the trainer, the module
and the data, the parser holds four sections: ``checkpoint`` (ModelCheckpoint: best by val/psnr),
``last_checkpoint`` (ModelCheckpoint: last.ckpt every N steps), ``throughput`` and ``wandb``, plus ``threads``
(torch CPU threads; default from ``aesplat.threads``: usable cores minus ``data.num_workers``). Everything
a run writes goes under ``trainer.default_root_dir`` (the run directory): checkpoints/, wandb/, config.yaml,
test/. ``--ckpt_path last`` resumes from the newest of
checkpoints/last.ckpt and a SLURM requeue checkpoint in that directory (and starts fresh when there is none).
With ``--ckpt_path FILE``, LightningCLI takes the whole ``model`` section from the checkpoint's hyper-parameters
(``model.cameras`` included), so a checkpoint evaluates as it was trained, whatever the config file says.
"""

from __future__ import annotations

import os
import signal
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_RUN_DIR = "outputs/run"


@dataclass
class WandbConfig:
    """Weights & Biases settings; the run id is fixed per run directory (resumes continue the same run)."""

    project: str = "aesplat"  # wandb project
    entity: str | None = None  # wandb team or user; default: your wandb default
    name: str | None = None  # display name; default: the run directory's name
    mode: str = "auto"  # auto (online if reachable, else offline) | online | offline | disabled
    tags: list[str] = field(default_factory=list)  # wandb run tags


def _lightning_cli():
    """Build the LightningCLI subclass (imports Lightning and the data/model stack only when needed)."""
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
    from lightning.pytorch.loggers import WandbLogger

    from aesplat.data import DataModule
    from aesplat.threads import apply_thread_policy
    from aesplat.train import AESplatModule
    from aesplat.train.callbacks import Throughput
    from aesplat.train.requeue import RequeueAtStepBoundary
    from aesplat.train.run_dir import latest_checkpoint, wandb_mode, wandb_run_id

    class AESplatCLI(LightningCLI):
        @staticmethod
        def subcommands() -> dict[str, set[str]]:
            commands = dict(LightningCLI.subcommands())
            commands.pop("predict")  # `aesplat predict` is the image-to-Gaussians command, not Lightning's
            return commands

        def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
            # Best by val/psnr (written after validation) and last (every N steps; a resume from any step,
            # mid-epoch included, continues exactly: see aesplat.data.stream).
            parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
            parser.add_lightning_class_args(ModelCheckpoint, "last_checkpoint")
            parser.set_defaults(
                {
                    "checkpoint.monitor": "val/psnr",
                    "checkpoint.mode": "max",
                    "checkpoint.save_top_k": 1,
                    "checkpoint.filename": "best-step{step}",
                    "checkpoint.auto_insert_metric_name": False,
                    "last_checkpoint.save_top_k": 0,
                    "last_checkpoint.save_last": True,
                    "last_checkpoint.every_n_train_steps": 1000,
                }
            )
            parser.add_lightning_class_args(Throughput, "throughput")
            parser.add_class_arguments(WandbConfig, "wandb")
            parser.add_argument(
                "--threads", type=int | None, default=None,
                help="torch CPU threads (default: usable cores minus data-loader workers; see aesplat.threads)",
            )  # fmt: skip

        def before_instantiate_classes(self) -> None:
            cfg = self.config[self.subcommand]
            run_dir = cfg.trainer.default_root_dir or DEFAULT_RUN_DIR
            cfg.trainer.default_root_dir = run_dir
            for key in ("checkpoint", "last_checkpoint"):
                if cfg[key].dirpath is None:
                    cfg[key].dirpath = str(Path(run_dir) / "checkpoints")
            apply_thread_policy(cfg.data.num_workers, cfg.threads, processes=_local_processes(cfg.trainer))

        def instantiate_trainer(self, **kwargs):
            cfg = self.config_init[self.subcommand]
            if cfg.trainer.get("logger") in (None, True):
                run_dir = Path(cfg.trainer.default_root_dir)
                wb = cfg.wandb
                mode = wandb_mode(wb.mode)
                extra = {"mode": "disabled"} if mode == "disabled" else {}
                kwargs["logger"] = WandbLogger(
                    project=wb.project, entity=wb.entity, name=wb.name or run_dir.name, save_dir=str(run_dir),
                    id=wandb_run_id(run_dir), offline=mode == "offline", tags=list(wb.tags), **extra,
                )  # fmt: skip
            trainer = super().instantiate_trainer(**kwargs)
            trainer.callbacks.append(RequeueAtStepBoundary())  # SLURM preemption between steps only
            return trainer

        def before_fit(self) -> None:
            fit = self.config_init["fit"]
            if fit.get("ckpt_path") == "last":
                found = latest_checkpoint(fit.trainer.default_root_dir)
                fit["ckpt_path"] = str(found) if found else None
                print(f"resuming from {found}" if found else "no checkpoint to resume from: starting fresh")

    return AESplatCLI, AESplatModule, DataModule


def _local_processes(trainer) -> int:
    """Training processes on this node that share its cores: the devices of a CPU run (DDP on the CPU)."""
    devices = trainer.get("devices")
    if trainer.get("accelerator") == "cpu" and isinstance(devices, int) and devices > 1:
        return devices
    return 1


# Lightning warnings that are expected here and would only bury real ones: the module moves its own typed
# batches (on purpose), and checkpoints of a manually optimized step hold the state after the update (as
# intended: the step counter has advanced with it).
_EXPECTED_WARNINGS = (
    r"You have overridden `(transfer_batch_to_device|on_after_batch_transfer)`",
    r"Using ModelCheckpoint with manual optimization",
)


# Keys older configs set that no longer exist, and what replaced them.
REMOVED_KEYS = {
    "data.near": "the depth range is the model's alone: set model.net.near (the data carry no depth range)",
    "data.far": "the depth range is the model's alone: set model.net.far (the data carry no depth range)",
}


def removed_key_error(argv: Sequence[str]) -> str | None:
    """One line naming the first removed key ``argv`` sets (``--key`` or a key of a ``-c`` file), or None."""
    import yaml

    for i, arg in enumerate(argv):
        key = arg[2:].split("=", 1)[0] if arg.startswith("--") else ""
        if key in REMOVED_KEYS:
            return f"aesplat: --{key} was removed; {REMOVED_KEYS[key]}"
        if arg in ("-c", "--config") and i + 1 < len(argv):
            path = Path(argv[i + 1])
        elif arg.startswith("--config="):
            path = Path(arg.split("=", 1)[1])
        else:
            continue
        if not path.is_file():
            continue  # LightningCLI says so
        config = yaml.safe_load(path.read_text()) or {}
        for dotted in REMOVED_KEYS:
            section, name = dotted.split(".")
            if isinstance(config.get(section), dict) and name in config[section]:
                return f"aesplat: {path} sets {dotted}, which was removed; {REMOVED_KEYS[dotted]}"
    return None


def run_lightning(argv: Sequence[str], module_class: type | None = None) -> None:
    """Run fit / validate / test through the LightningCLI (``module_class``: a subclass of AESplatModule)."""
    if error := removed_key_error(argv):
        raise SystemExit(error)
    for pattern in _EXPECTED_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    cli_class, default_module, data_class = _lightning_cli()
    module_class = module_class or default_module
    cli_class(
        module_class,
        data_class,
        args=None if list(argv) == sys.argv[1:] else list(argv),  # None: LightningCLI reads sys.argv itself
        parser_kwargs={"parser_mode": "omegaconf"},
        save_config_kwargs={"overwrite": True},
        auto_configure_optimizers=False,
    )


def hold_requeue_signal() -> bool:
    """Inside a SLURM job, block SIGUSR1 (the requeue signal) in this thread; True if it did so.

    Called before torch is imported (which starts a thread): every thread and process started afterwards
    inherits the mask, so the signal waits, pending, for ``aesplat.train.requeue.RequeueAtStepBoundary``.
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
        print("aesplat predict --help                    images -> Gaussians, cameras, renders")
        print("aesplat bench --help                      accuracy-versus-time report\n")
        argv = ["--help"]
    if argv and argv[0] == "predict":
        from aesplat.predict import main as predict_main

        predict_main(argv[1:])
    elif argv and argv[0] == "bench":
        from aesplat.tradeoffs import main as bench_main

        bench_main(argv[1:])
    else:
        run_lightning(argv)


if __name__ == "__main__":
    main()
