"""`aesplat fit|validate|test`: training and evaluation, a LightningCLI.

    aesplat fit|validate|test -c conf/FILE.yaml [-c conf/OVERLAY.yaml …] [--dotted.key value …]

The parser is in OmegaConf mode (``${…}`` interpolation inside a file, several ``-c`` files layered left to
right, ``--print_config`` to see the result). Besides the trainer, the module and the data, it holds five
sections: ``checkpoint`` (best by val/psnr), ``last_checkpoint`` (last.ckpt every N steps and at the end of
every fit), ``throughput``, ``wandb`` and ``distributed`` (how long DDP ranks wait for each other), plus
``threads`` (torch CPU threads; default from ``aesplat.threads``: usable cores minus ``data.num_workers``).
Everything a run writes goes under ``trainer.default_root_dir`` (the run directory): checkpoints/, wandb/,
config.yaml; each test / validate writes its config.yaml and results into
a folder of its own, ``test-<UTC time>/`` (under ``model.eval.output_dir`` if set, else the run directory), the
newest behind the link ``test-latest``: an evaluation never changes the training run's files.

``fit`` refuses a run directory that already holds a run unless ``--ckpt_path last`` (resume) or
``--overwrite`` (delete it and start afresh; never a folder holding the current one, the home folder or one
of the run's inputs), and a run directory another ``aesplat fit`` is training in (a lock). A fit that stops
before its first checkpoint takes back its run markers (config.yaml, wandb id). Checkpoints are written
atomically (``aesplat.train.checkpoint_io``); a fit stopped by a signal saves where it stopped and exits with
128 + the signal (``aesplat.train.signals``).

``--ckpt_path FILE|last|best`` goes through ``aesplat.checkpoint``, the loading path every command shares:
``last`` is the newest checkpoint of the run directory that loads (``fit`` starts fresh when there is none),
``best`` the one with the best validation score; the file is read safely, and its hyper-parameters are
checked (values of known settings, never a class) before they replace the ``model`` section, so a checkpoint
evaluates or resumes as it was trained, whatever the config file says; a ``--model.*`` flag that the
checkpoint overrides is named on stderr. ``model.eval`` (where and what an evaluation writes) stays the
command's.

The inputs (config values, data root, checkpoint, weights file, run directory) are checked before anything is
created or loaded; a user's error stops with one line (``AESPLAT_DEBUG=1``: with its traceback), see
docs/troubleshooting.md.
"""

from __future__ import annotations

import os
import re
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import timedelta
from pathlib import Path

from jsonargparse import ActionYesNo
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback
from lightning.pytorch.plugins.io import CheckpointIO
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.utilities.exceptions import MisconfigurationException

from aesplat.checkpoint import checked_hparams, checkpoint_sections, read_checkpoint, resolve_ckpt_path
from aesplat.commands import OneLineParser
from aesplat.config_checks import check_config
from aesplat.data import DataModule
from aesplat.errors import (
    MissingFileError,
    RanksLost,
    RanksTooSlow,
    Stopped,
    UserError,
    check_writable,
    signal_name,
)
from aesplat.files import check_deletable, remove_partials
from aesplat.model.nas3r import is_nas3r_state, nas3r_net, nas3r_variant
from aesplat.threads import apply_thread_policy
from aesplat.train import AESplatModule
from aesplat.train.callbacks import DataRecord, RunCheckpoint, Throughput
from aesplat.train.checkpoint_io import AtomicCheckpointIO
from aesplat.train.logger import SteadyWandbLogger
from aesplat.train.run_dir import FitWrites, lock_run, point_latest, wandb_mode, wandb_run_id
from aesplat.train.signals import SignalsAtStepBoundary, end_started_ranks

DEFAULT_RUN_DIR = "outputs/run"


@dataclass
class WandbConfig:
    """Weights & Biases settings; the run id is fixed per run directory (resumes continue the same run)."""

    project: str = "aesplat"  # wandb project
    entity: str | None = None  # wandb team or user; default: your wandb default
    name: str | None = None  # display name; default: the run directory's name
    mode: str = "auto"  # auto (online if reachable, else offline) | online | offline | disabled
    tags: list[str] = field(default_factory=list)  # wandb run tags


@dataclass
class DistributedConfig:
    """Multi-process (DDP) training: how long the ranks wait for each other."""

    # seconds a collective waits for every rank before the run ends saying which rank was lost, or which was
    # slow (torch's default is 30 minutes); raise it where a checkpoint save or a rank's first batch takes
    # minutes. 10 s to 7 days: the ranks must also start and join the process group within it
    timeout: float = 300.0


class LightningParser(OneLineParser, LightningArgumentParser):
    """The parser of `aesplat fit|validate|test` and of each subcommand: an error is one line, the key and what
    is wrong."""

    def command(self) -> str:
        name = (self.prog or "").replace(" [options]", "").split()[-1:] or ["fit"]
        return "aesplat " + (name[0] if name[0] in AESplatCLI.subcommands() else "fit|validate|test")

    def error_line(self, message: str) -> str:
        return parser_error_line(message)


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
    # Called when the command fails or stops (a fit that saved no checkpoint takes back its run markers).
    on_failure: list[Callable[[], object]] = []
    signals: SignalsAtStepBoundary | None = None  # of the command under way: says when a DDP rank was lost
    launcher: object | None = None  # Lightning's, of the command under way: the ranks it started end with it

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        commands = dict(LightningCLI.subcommands())
        commands.pop("predict")  # `aesplat predict` is the image-to-Gaussians command, not Lightning's
        return commands

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        # Best by val/psnr (written after validation) and last (every N steps and at the end; a resume from
        # any step, mid-epoch included, continues exactly: see aesplat.data.stream). Always the same file
        # names: a run folder holds one run.
        parser.add_lightning_class_args(RunCheckpoint, "checkpoint")
        parser.add_lightning_class_args(RunCheckpoint, "last_checkpoint")
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
        parser.add_class_arguments(DistributedConfig, "distributed")
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
        """Replaces Lightning's: ``--ckpt_path FILE|last|best`` resolved and read through
        ``aesplat.checkpoint`` (its checked settings replace the ``model`` section, ``model.eval`` kept),
        then every config value and input checked, all before anything is written."""
        sub = self.config.get("subcommand")
        if not sub:
            return
        cfg = self.config[sub]
        cfg.trainer.default_root_dir = cfg.trainer.default_root_dir or DEFAULT_RUN_DIR
        run_dir = Path(cfg.trainer.default_root_dir)
        asked = cfg.get("ckpt_path")
        if asked:
            if sub == "fit" and asked == "last" and cfg.overwrite:
                raise UserError("--overwrite deletes the run that --ckpt_path last would resume: give one")
            if asked not in ("last", "best") and not Path(asked).exists():
                resume = ", or `--ckpt_path last` to resume the run in --trainer.default_root_dir"
                raise MissingFileError(
                    f"--ckpt_path {asked} does not exist: give RUN/checkpoints/last.ckpt of `aesplat fit`"
                    + (resume if sub == "fit" else "")
                )
            fresh = sub == "fit" and asked == "last"
            path, skipped = resolve_ckpt_path(asked, run_dir, cfg.checkpoint.monitor, cfg.checkpoint.mode,
                                              fresh_if_none=fresh)  # fmt: skip
            for problem in skipped:
                print(f"aesplat {sub}: {problem}; skipped", file=sys.stderr)
            if path is None:
                print("no checkpoint to resume from: starting fresh")
            else:
                ckpt = read_checkpoint(path)
                self._take_model_from_checkpoint(sub, ckpt, path)
                if asked in ("last", "best"):
                    step = ckpt.get("global_step")
                    verb = "resuming from" if sub == "fit" else f"--ckpt_path {asked}:"
                    print(f"{verb} {path} (step {step})" + (", the newest that loads" if skipped else ""))
            self.config[sub].ckpt_path = None if path is None else str(path)
        # Before the seed is set: a refusal prints nothing else.
        check_config(sub, self.config[sub])
        check_inputs(sub, self.config[sub], resuming=bool(asked))

    def _take_model_from_checkpoint(self, sub: str, ckpt: dict, path: Path) -> None:
        """The checkpoint's checked model settings replace the command's; name the flags they override."""
        before = self.config[sub].clone()
        sections = checkpoint_sections()
        if is_nas3r_state(ckpt["state_dict"]):  # NAS3R's own: its network, as this project names it
            if sub == "fit":
                raise UserError(f"--ckpt_path {path} is NAS3R's: `aesplat fit` resumes its own runs only; "
                                f"start from NAS3R's weights with --model.net.weights {path}")  # fmt: skip
            settings = {"net": nas3r_net(nas3r_variant(ckpt["state_dict"], path)), "cameras": "predicted"}
        else:
            settings = checked_hparams(ckpt, path, sections)
        settings.pop("eval", None)  # where and what an evaluation writes is the command's
        try:  # each section whole (the defaults of this version where the checkpoint predates a key)
            model = {
                name: value if name == "cameras" else asdict(sections[name](**value))
                for name, value in settings.items()
            }
        except (TypeError, ValueError) as err:
            raise UserError(f"checkpoint {path}: {err}") from None
        if model:
            self.parser.exit_on_error = False
            try:
                self.config = self.parser.parse_object({sub: {"model": model}}, self.config)
            except Exception as err:  # noqa: BLE001 - jsonargparse's own error types vary by version
                raise UserError(f"checkpoint {path}: its model settings do not fit this version "
                                f"({parser_error_line(str(err))})") from None  # fmt: skip
            finally:
                self.parser.exit_on_error = True
        cfg = self.config[sub]
        cfg.model.eval = before.model.eval
        for key in explicit_keys(self.argv, "model."):
            if key.startswith("model.eval") or before.get(key) == cfg.get(key):
                continue
            print(f"aesplat {sub}: --{key} {before.get(key)} has no effect: the checkpoint {path} "
                  f"sets it to {cfg.get(key)} (with --ckpt_path, the checkpoint's model settings win)",
                  file=sys.stderr)  # fmt: skip

    def before_instantiate_classes(self) -> None:
        cfg = self.config[self.subcommand]
        run_dir = Path(cfg.trainer.default_root_dir)
        if self.subcommand == "fit" and launching_process():
            inputs = fit_inputs(cfg, self.argv)
            if cfg.overwrite:
                check_deletable(run_dir, "--overwrite", inputs)
            writes = FitWrites(run_dir)
            lock_run(run_dir)  # one fit at a time in a run folder, from here to the end of the process
            if cfg.overwrite:
                clear_run_dir(run_dir, inputs)
            writes.snapshot()
            self.on_failure.append(writes.discard_if_untrained)
            remove_partials(run_dir / "checkpoints")  # of a save that was killed
        if self.subcommand in ("test", "validate"):
            cfg.model.eval.output_dir = shared_evaluation_dir(
                cfg.model.eval.output_dir or run_dir, self.subcommand
            )
        for key in ("checkpoint", "last_checkpoint"):
            if cfg[key].dirpath is None:
                cfg[key].dirpath = str(run_dir / "checkpoints")
        apply_thread_policy(cfg.data.num_workers, cfg.threads, processes=_local_processes(cfg.trainer))

    def instantiate_classes(self) -> None:
        try:
            super().instantiate_classes()
            self.model.step_tracker = self.datamodule.step_tracker
        except UserError:
            raise
        except ValueError as err:  # a config value the model or the data refuse (size, near/far, ...)
            raise UserError(f"invalid configuration: {parser_error_line(str(err))}") from err

    def instantiate_trainer(self, **kwargs):
        cfg = self.config_init[self.subcommand]
        if cfg.trainer.get("logger") in (None, True):
            run_dir = Path(cfg.trainer.default_root_dir)
            wb = cfg.wandb
            mode = wandb_mode(wb.mode)
            extra = {"mode": "disabled"} if mode == "disabled" else {}
            kwargs["logger"] = SteadyWandbLogger(
                project=wb.project, entity=wb.entity, name=wb.name or run_dir.name, save_dir=str(run_dir),
                id=wandb_run_id(run_dir), offline=mode == "offline", tags=list(wb.tags), **extra,
            )  # fmt: skip
        plugins = cfg.trainer.get("plugins") or []
        plugins = list(plugins) if isinstance(plugins, (list, tuple)) else [plugins]
        if not any(isinstance(p, CheckpointIO) for p in plugins):  # checkpoints written whole, read safely
            kwargs["plugins"] = [*plugins, AtomicCheckpointIO()]
        try:
            trainer = super().instantiate_trainer(**kwargs)
        except MisconfigurationException as err:  # a trainer value Lightning refuses: devices, ...
            raise UserError(f"invalid configuration: trainer: {str(err).strip().splitlines()[0]}") from None
        timeout = cfg.distributed.timeout  # in range: config_checks
        if isinstance(trainer.strategy, DDPStrategy):  # its process group is made when the fit starts
            trainer.strategy._timeout = timedelta(seconds=timeout)
        AESplatCLI.launcher = trainer.strategy.launcher
        # stop and SLURM requeue between steps only; a lost DDP rank named
        AESplatCLI.signals = self.signals = SignalsAtStepBoundary(timeout=timeout)
        trainer.callbacks += [self.signals, DataRecord()]
        return trainer

    def after_fit(self) -> None:
        """A fit a signal stopped ends with 128 + the signal, saying where it stopped and what it saved."""
        signum = self.signals.stop_signal
        if signum is None:
            return
        saved = [
            c.last_model_path for c in self.trainer.checkpoint_callbacks if getattr(c, "last_model_path", "")
        ]
        where = f"saved {saved[-1]}" if saved else "nothing to save yet"
        step = self.trainer.global_step
        raise Stopped(signum, f"stopped by {signal_name(signum)} after step {step}; {where}: resume with "
                      "--ckpt_path last")  # fmt: skip

    def after_test(self) -> None:
        self._point_latest()

    def after_validate(self) -> None:
        self._point_latest()

    def _point_latest(self) -> None:
        if self.trainer.is_global_zero:
            folder = self.model.test_output_dir
            folder.mkdir(parents=True, exist_ok=True)
            print(f"aesplat {self.subcommand}: results in {folder} (also {point_latest(folder)})")


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


def config_files(argv: Sequence[str]) -> list[Path]:
    """The files given with ``-c FILE`` / ``--config FILE`` / ``--config=FILE``, in order."""
    files = []
    for i, arg in enumerate(argv):
        if arg in ("-c", "--config") and i + 1 < len(argv):
            files.append(Path(argv[i + 1]))
        elif arg.startswith("--config="):
            files.append(Path(arg.split("=", 1)[1]))
    return files


def read_config_file(path: Path) -> dict:
    """A ``-c`` file as a mapping; UserError naming the file, line and column of a YAML error."""
    import yaml

    try:
        config = yaml.safe_load(path.read_text())
    except UnicodeDecodeError:
        raise UserError(f"-c {path} is not a text file: give a YAML config") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        tab = "\t" in path.read_text().splitlines()[mark.line] if mark else False
        fix = ": indent with spaces, YAML does not allow tabs" if tab else ""
        raise UserError(f"-c {path} is not valid YAML{where} ({problem}){fix}") from None
    if config is None:
        return {}
    if not isinstance(config, dict):
        kind = type(config).__name__
        raise UserError(f"-c {path} holds a {kind}, not a mapping of sections (trainer:, model:, data:, ...)")
    return config


def launching_process() -> bool:
    """Whether this is the process a user started (not a DDP rank Lightning or SLURM started beside it)."""
    return all(os.environ.get(v, "0") == "0" for v in ("LOCAL_RANK", "NODE_RANK", "SLURM_PROCID"))


def check_inputs(command: str, cfg, resuming: bool = False) -> None:
    """Every input a run needs, checked before the trainer, wandb or the model start (one line each).
    ``resuming``: ``--ckpt_path`` was given (``last`` with nothing to resume from included)."""
    from aesplat.data.datamodule import check_target_count, find_shards, validation_split
    from aesplat.model.weights import read_torch_file
    from aesplat.train.run_dir import run_artifacts

    run_dir = Path(cfg.trainer.default_root_dir)
    ckpt_path = cfg.get("ckpt_path")
    if command == "fit":
        find_shards(cfg.data.root, "train")
        trainer = cfg.trainer
        validates = trainer.get("limit_val_batches") != 0 and trainer.get("check_val_every_n_epoch") is not None
        # validation runs on the validation split; on the test split only when data.validate_on_test asks
        split = validation_split(cfg.data.root, cfg.data.get("validate_on_test", False)) if validates else None
    elif command == "validate":  # the split validation runs on, as fit's validation
        split = validation_split(cfg.data.root, cfg.data.get("validate_on_test", False))
    else:
        split = cfg.data.get("test_split", "test")
    if split is not None:  # the split evaluated
        find_shards(cfg.data.root, split)
        check_target_count(cfg.data.root, split, cfg.data.get("eval_num_target_views"))
    if command == "fit":
        held = run_artifacts(run_dir) if launching_process() else []
        if held and ckpt_path is None and not resuming and not cfg.overwrite:
            raise UserError(
                f"{run_dir} already holds a run ({held[0].relative_to(run_dir)}): resume it with --ckpt_path "
                "last, give a new --trainer.default_root_dir, or --overwrite to delete it and start afresh"
            )
    weights = cfg.model.net.get("weights") if cfg.model.get("net") else None
    if weights:
        read_torch_file(weights, "--model.net.weights")
    writable_parent(run_dir, "--trainer.default_root_dir")
    if command != "fit" and cfg.model.eval.get("output_dir"):
        writable_parent(Path(cfg.model.eval.output_dir), "--model.eval.output_dir")


def fit_inputs(cfg, argv: Sequence[str]) -> list[tuple[str, str | Path | None]]:
    """What ``aesplat fit`` reads, named by its option: ``--overwrite`` never deletes a folder holding one."""
    weights = cfg.model.net.get("weights") if cfg.model.get("net") else None
    return [("--data.root", cfg.data.root), ("--ckpt_path", cfg.get("ckpt_path")),
            ("--model.net.weights", weights), *(("-c", path) for path in config_files(argv))]  # fmt: skip


def writable_parent(folder: Path, flag: str) -> None:
    """``folder`` is (or can be made) a folder this process may write into."""
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{flag} {folder} is a file, not a folder")
    check_writable(folder, f"{flag} {folder}")


def clear_run_dir(run_dir: str | Path, inputs: Sequence[tuple[str, str | Path | None]] = ()) -> None:
    """``--overwrite``: delete what the run directory holds (its lock stays with this process), never a
    folder holding the current folder, the home folder or one of the run's ``inputs``."""
    from aesplat.files import delete_folder
    from aesplat.train.run_dir import LOCK_FILE

    run_dir = Path(run_dir)
    existed = run_dir.exists() and any(p.name != LOCK_FILE for p in run_dir.iterdir())
    delete_folder(run_dir, "--overwrite", inputs, keep=(LOCK_FILE,))
    if existed:
        print(f"aesplat fit: --overwrite: deleted what {run_dir} held", file=sys.stderr)


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
    """One line naming the first removed key ``argv`` sets (``--key`` or a key of a ``-c`` file), or None.
    A ``-c`` file that is not a YAML mapping is refused on the way (UserError)."""
    for arg in argv:
        key = arg[2:].split("=", 1)[0] if arg.startswith("--") else ""
        if key in REMOVED_KEYS:
            return f"--{key} was removed; {REMOVED_KEYS[key]}"
    for path in config_files(argv):
        if not path.is_file():
            continue  # LightningCLI says so
        config = read_config_file(path)
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
    AESplatCLI.on_failure, AESplatCLI.signals, AESplatCLI.launcher = [], None, None
    try:
        AESplatCLI(
            module_class or AESplatModule,
            DataModule,
            args=None if list(argv) == sys.argv[1:] else list(argv),  # None: LightningCLI reads sys.argv itself
            parser_kwargs={"parser_mode": "omegaconf"},
            parser_class=LightningParser,
            save_config_callback=SaveRunConfig,
            save_config_kwargs={"overwrite": True},
            auto_configure_optimizers=False,
        )
    except BaseException as err:
        # The ranks this process started first: none may write into the run folder after its cleanup.
        end_started_ranks(AESplatCLI.launcher)
        for cleanup in AESplatCLI.on_failure:
            cleanup()
        signals = AESplatCLI.signals
        if signals is not None and signals.lost:
            raise RanksLost(signals.lost) from err
        if signals is not None and signals.slow:
            raise RanksTooSlow(signals.slow) from err
        raise
