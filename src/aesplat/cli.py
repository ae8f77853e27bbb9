"""The `aesplat` command.

    aesplat fit|validate|test -c conf/FILE.yaml [-c conf/OVERLAY.yaml …] [--dotted.key value …]
    aesplat predict …     (aesplat.predict)
    aesplat bench …       (aesplat.bench)
    aesplat export …      (aesplat.export.command)
    aesplat view …        (aesplat.view)

fit/validate/test are a LightningCLI in OmegaConf parser mode (``${…}`` interpolation inside a file, several
``-c`` files layered left to right, ``--print_config`` to see the result). Besides the trainer, the module
and the data, the parser holds four sections: ``checkpoint`` (ModelCheckpoint: best by val/psnr),
``last_checkpoint`` (ModelCheckpoint: last.ckpt every N steps), ``throughput`` and ``wandb``, plus ``threads``
(torch CPU threads; default from ``aesplat.threads``: usable cores minus ``data.num_workers``). Everything
a run writes goes under ``trainer.default_root_dir`` (the run directory): checkpoints/, wandb/, config.yaml;
each test / validate writes its config.yaml and results into a folder of its own, ``test-<UTC time>/`` (under
``model.eval.output_dir`` if set, else the run directory), the newest behind the link ``test-latest``: an
evaluation never changes the training run's files. ``fit`` refuses a run directory that already holds a run
unless ``--ckpt_path last`` (resume) or ``--overwrite`` (delete it and start afresh). ``--ckpt_path last``
resumes from the newest of checkpoints/last.ckpt and a SLURM requeue checkpoint in that directory (and starts
fresh when there is none). With ``--ckpt_path FILE``, LightningCLI takes the ``model`` section from the
checkpoint's hyper-parameters (``model.cameras`` included), so a checkpoint evaluates as it was trained,
whatever the config file says; a ``--model.*`` flag that the checkpoint overrides is named on stderr.
``model.eval`` (where and what an evaluation writes) stays the command's.

The inputs (data root, checkpoint, weights file, run directory) are checked before anything is created or
loaded; a user's error stops with one line (``AESPLAT_DEBUG=1``: with its traceback), see
docs/troubleshooting.md.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from aesplat.errors import MissingFileError, UserError, check_writable, debug, run_reporting_user_errors

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
    from jsonargparse import ActionYesNo
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback
    from lightning.pytorch.loggers import WandbLogger

    from aesplat.data import DataModule
    from aesplat.threads import apply_thread_policy
    from aesplat.train import AESplatModule
    from aesplat.train.callbacks import Throughput
    from aesplat.train.requeue import RequeueAtStepBoundary
    from aesplat.train.run_dir import latest_checkpoint, point_latest, wandb_mode, wandb_run_id

    class OneLineParser(LightningArgumentParser):
        """A command-line or config error is one line (the key and what is wrong), not the usage text."""

        def error(self, message: str, ex: Exception | None = None):
            if debug() or not self.exit_on_error:
                return super().error(message, ex)
            command = (self.prog or "").replace(" [options]", "").split()[-1:] or ["fit"]
            command = command[0] if command[0] in ("fit", "validate", "test") else "fit|validate|test"
            hint = f"`aesplat {command} --help` lists the options"
            print(f"aesplat {command}: {parser_error_line(message)} ({hint})", file=sys.stderr)
            raise SystemExit(2)  # a malformed command line, as argparse

    class SaveRunConfig(SaveConfigCallback):
        """config.yaml where the command's outputs go: the run directory (fit), or the evaluation's own folder
        (test / validate), so an evaluation never rewrites the training run's config."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **{**kwargs, "save_to_log_dir": False})

        def save_config(self, trainer, pl_module, stage: str) -> None:
            folder = Path(trainer.default_root_dir) if stage == "fit" else pl_module.test_output_dir
            folder.mkdir(parents=True, exist_ok=True)
            with warnings.catch_warnings():  # skip_none as Lightning passes it: None values kept
                warnings.filterwarnings("ignore", message=r"\s*skip_none parameter was deprecated")
                self.parser.save(self.config, str(folder / self.config_filename), skip_none=False,
                                 overwrite=True, multifile=self.multifile)  # fmt: skip

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
            parser.add_argument(
                "--overwrite", action=ActionYesNo, default=False,
                help="fit: delete a run directory that holds a run and start afresh (default: refuse)",
            )  # fmt: skip

        def parse_arguments(self, parser, args) -> None:
            self.argv = list(sys.argv[1:] if args is None else args)
            super().parse_arguments(parser, args)

        def _parse_ckpt_path(self) -> None:
            """Check ``--ckpt_path`` before Lightning reads it; name each ``--model.*`` flag it overrides; keep
            the command's ``model.eval`` (where and what the evaluation writes)."""
            sub = self.config.get("subcommand")
            if not sub:
                return
            cfg = self.config[sub]
            cfg.trainer.default_root_dir = cfg.trainer.default_root_dir or DEFAULT_RUN_DIR
            ckpt_path = cfg.get("ckpt_path")
            if ckpt_path and not (sub == "fit" and ckpt_path == "last"):
                check_lightning_checkpoint(ckpt_path, sub)
                self._take_model_from_checkpoint(sub, ckpt_path)
            check_inputs(sub, self.config[sub])  # before the seed is set: a refusal prints nothing else

        def _take_model_from_checkpoint(self, sub: str, ckpt_path: str) -> None:
            before = self.config[sub].clone()
            super()._parse_ckpt_path()
            cfg = self.config[sub]
            cfg.model.eval = before.model.eval
            for key in explicit_keys(self.argv, "model."):
                if key.startswith("model.eval") or before.get(key) == cfg.get(key):
                    continue
                print(f"aesplat {sub}: --{key} {before.get(key)} has no effect: the checkpoint {ckpt_path} "
                      f"sets it to {cfg.get(key)} (with --ckpt_path, the checkpoint's model settings win)",
                      file=sys.stderr)  # fmt: skip

        def before_instantiate_classes(self) -> None:
            cfg = self.config[self.subcommand]
            run_dir = cfg.trainer.default_root_dir
            if self.subcommand == "fit" and cfg.overwrite and launching_process():
                clear_run_dir(run_dir)
            if self.subcommand in ("test", "validate"):
                cfg.model.eval.output_dir = shared_evaluation_dir(
                    cfg.model.eval.output_dir or run_dir, self.subcommand
                )
            for key in ("checkpoint", "last_checkpoint"):
                if cfg[key].dirpath is None:
                    cfg[key].dirpath = str(Path(run_dir) / "checkpoints")
            apply_thread_policy(cfg.data.num_workers, cfg.threads, processes=_local_processes(cfg.trainer))

        def instantiate_classes(self) -> None:
            try:
                super().instantiate_classes()
            except UserError:
                raise
            except ValueError as err:  # a config value the model or the data refuse (size, near/far, ...)
                raise UserError(f"invalid configuration: {err}") from err

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

        def after_test(self) -> None:
            self._point_latest()

        def after_validate(self) -> None:
            self._point_latest()

        def _point_latest(self) -> None:
            if self.trainer.is_global_zero:
                folder = self.model.test_output_dir
                folder.mkdir(parents=True, exist_ok=True)
                print(f"aesplat {self.subcommand}: results in {folder} (also {point_latest(folder)})")

    return AESplatCLI, AESplatModule, DataModule, OneLineParser, SaveRunConfig


# ---------------------------------------------------------------------------------------------------
# Inputs checked before anything is created or loaded


def parser_error_line(message: str) -> str:
    """The one useful line of a jsonargparse error: the key, and the innermost reason it gives."""
    lines = [line.strip() for line in message.strip().splitlines() if line.strip()]
    key = re.match(r'Parser key "([^"]+)":?', lines[0]) if lines else None
    reason = re.compile(r"not accepted|Expected|Got value|not found|does not|No such|[Uu]nrecogni|[Ii]nvalid")
    reasons = [line for line in lines[1:] if reason.search(line)]
    if key and reasons:
        return f"{key.group(1)}: {reasons[0]}"
    return lines[0] if lines else message


def explicit_keys(argv: Sequence[str], prefix: str) -> list[str]:
    """Dotted keys given as ``--KEY value`` or ``--KEY=value`` flags on the command line, under ``prefix``."""
    keys = [a[2:].split("=", 1)[0] for a in argv if a.startswith("--" + prefix)]
    return [k.removesuffix("+") for k in keys]


def launching_process() -> bool:
    """Whether this is the process a user started (not a DDP rank Lightning or SLURM started beside it)."""
    return all(os.environ.get(v, "0") == "0" for v in ("LOCAL_RANK", "NODE_RANK", "SLURM_PROCID"))


def check_lightning_checkpoint(path: str, command: str) -> None:
    """``--ckpt_path FILE`` must be a readable Lightning checkpoint; the error names what the file is."""
    from aesplat.model.weights import KIND_NAMES, checkpoint_kind, read_torch_file

    if command != "fit" and path in ("last", "best"):
        return
    if not Path(path).is_file():
        raise MissingFileError(
            f"--ckpt_path {path} does not exist: give RUN/checkpoints/last.ckpt of `aesplat fit`"
            + (
                ", or `--ckpt_path last` to resume the run in --trainer.default_root_dir"
                if command == "fit"
                else ""
            )
        )
    kind = checkpoint_kind(read_torch_file(path, "checkpoint"))
    if kind == "lightning":
        return
    hint = (
        "give it as --model.net.weights FILE instead" if kind != "other" else "give RUN/checkpoints/last.ckpt"
    )
    raise UserError(f"--ckpt_path {path} is {KIND_NAMES[kind]}, not a Lightning checkpoint: {hint}")


def check_inputs(command: str, cfg) -> None:
    """Every input a run needs, checked before the trainer, wandb or the model start (one line each)."""
    from aesplat.data.datamodule import find_shards, validation_split
    from aesplat.model.weights import read_torch_file
    from aesplat.train.run_dir import run_artifacts

    run_dir = Path(cfg.trainer.default_root_dir)
    ckpt_path = cfg.get("ckpt_path")
    if command == "fit":
        find_shards(cfg.data.root, "train")
        if cfg.trainer.get("limit_val_batches") != 0 and cfg.trainer.get("check_val_every_n_epoch") is not None:
            # validation runs on the validation split; on the test split only when data.validate_on_test asks
            find_shards(cfg.data.root, validation_split(cfg.data.root, cfg.data.get("validate_on_test", False)))
        held = run_artifacts(run_dir) if launching_process() else []
        if held and ckpt_path is None and not cfg.overwrite:
            raise UserError(
                f"{run_dir} already holds a run ({held[0].relative_to(run_dir)}): resume it with --ckpt_path "
                "last, give a new --trainer.default_root_dir, or --overwrite to delete it and start afresh"
            )
    else:
        find_shards(cfg.data.root, "test")
    weights = cfg.model.net.get("weights") if cfg.model.get("net") else None
    if weights:
        read_torch_file(weights, "--model.net.weights")
    writable_parent(run_dir, "--trainer.default_root_dir")
    if command != "fit" and cfg.model.eval.get("output_dir"):
        writable_parent(Path(cfg.model.eval.output_dir), "--model.eval.output_dir")


def writable_parent(folder: Path, flag: str) -> None:
    """``folder`` is (or can be made) a folder this process may write into."""
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{flag} {folder} is a file, not a folder")
    check_writable(folder, f"{flag} {folder}")


def clear_run_dir(run_dir: str | Path) -> None:
    """``--overwrite``: delete the run directory (never the current folder, one holding it, or the home)."""
    run_dir = Path(run_dir).resolve()
    cwd = Path.cwd().resolve()
    if run_dir in (cwd, *cwd.parents, Path.home().resolve()):
        raise UserError(f"--overwrite will not delete {run_dir}: give a run directory of its own")
    if run_dir.exists():
        shutil.rmtree(run_dir)
        print(f"aesplat fit: --overwrite: deleted {run_dir}", file=sys.stderr)


def shared_evaluation_dir(base: str | Path, command: str) -> str:
    """The evaluation folder of this command, the same in every DDP rank Lightning starts from this one."""
    from aesplat.train.run_dir import evaluation_dir

    env = "AESPLAT_EVALUATION_DIR"
    if not launching_process() and os.environ.get(env):
        return os.environ[env]
    os.environ[env] = str(evaluation_dir(base, command))  # inherited by the ranks started later
    return os.environ[env]


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
            return f"--{key} was removed; {REMOVED_KEYS[key]}"
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
                return f"{path} sets {dotted}, which was removed; {REMOVED_KEYS[dotted]}"
    return None


def run_lightning(argv: Sequence[str], module_class: type | None = None) -> None:
    """Run fit / validate / test through the LightningCLI (``module_class``: a subclass of AESplatModule)."""
    if error := removed_key_error(argv):
        raise UserError(error)
    for pattern in _EXPECTED_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    cli_class, default_module, data_class, parser_class, save_config = _lightning_cli()
    module_class = module_class or default_module
    cli_class(
        module_class,
        data_class,
        args=None if list(argv) == sys.argv[1:] else list(argv),  # None: LightningCLI reads sys.argv itself
        parser_kwargs={"parser_mode": "omegaconf"},
        parser_class=parser_class,
        save_config_callback=save_config,
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
        print("aesplat bench --help                      accuracy-versus-time report")
        print("aesplat export --help                     a prediction for COLMAP, nerfstudio, web viewers")
        print("aesplat view --help                       a prediction in the browser\n")
        argv = ["--help"]
    command = (
        argv[0]
        if argv and argv[0] in ("predict", "bench", "export", "view", "fit", "validate", "test")
        else "fit|validate|test"
    )
    # A UserError is the user's to mend: one line; anything else is a bug and keeps its traceback.
    run_reporting_user_errors(command, lambda: _run_command(command, argv))


def _run_command(command: str, argv: list[str]) -> None:
    if command == "predict":
        from aesplat.predict import main as predict_main

        predict_main(argv[1:])
    elif command == "bench":
        from aesplat.bench import main as bench_main

        bench_main(argv[1:])
    elif command == "export":
        from aesplat.export.command import main as export_main

        export_main(argv[1:])
    elif command == "view":
        from aesplat.view import main as view_main

        view_main(argv[1:])
    else:
        run_lightning(argv)


if __name__ == "__main__":
    main()
