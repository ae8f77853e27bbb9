"""`aesplat fit|test|validate`: a user's mistake stops with one line before anything is written or loaded.

Each case asserts the exit status, the single line, and the file system afterwards. The commands run in this
process (the exit goes through SystemExit, as the console script's); one subprocess checks the real entry
point's stderr and ``AESPLAT_DEBUG=1``.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from aesplat import cli
from aesplat.errors import UserError
from aesplat.lightning_cli import check_inputs, clear_run_dir, explicit_keys, parser_error_line
from aesplat.model.weights import export_weights
from tests.helpers import REPO, aesplat, common, make_shards, one_line, write_tiny_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """A Lightning checkpoint (RUN/checkpoints/last.ckpt), its exported weights, a truncated copy, garbage."""
    folder = tmp_path_factory.mktemp("ckpts")
    last = write_tiny_checkpoint(folder / "run")
    exported = export_weights(last, folder / "exported.pt")
    truncated = folder / "truncated.ckpt"
    truncated.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
    garbage = folder / "garbage.ckpt"
    garbage.write_text("definitely not a checkpoint\n")
    return {"last": last, "exported": exported, "truncated": truncated, "garbage": garbage}


@pytest.mark.parametrize("command", ["fit", "test", "validate"])
def test_missing_or_empty_data_root(command, capsys, tmp_path):
    run_dir = tmp_path / "run"
    code, err = aesplat(capsys, command, *common(tmp_path / "nowhere", run_dir))
    assert code == 1
    assert one_line(err) == (
        f"aesplat {command}: no shards in {tmp_path / 'nowhere'}: the folder does not exist; give the folder "
        "`python data_prep/to_shards.py --out` wrote, or create it with that command"
    )
    (tmp_path / "empty").mkdir()
    code, err = aesplat(capsys, command, *common(tmp_path / "empty", run_dir))
    split = "train" if command == "fit" else "test"
    assert code == 1 and one_line(err).startswith(
        f"aesplat {command}: no shards in {tmp_path / 'empty' / split}"
    )
    assert not run_dir.exists()  # no config.yaml, wandb/ or wandb_run_id before the inputs were checked


def test_fit_checks_the_split_validation_runs_on(tmp_path):
    """Shards with a validation split and no test split train (validation needs no test scene); their
    validation shards must be there."""
    from jsonargparse import Namespace

    root = make_shards(tmp_path, scenes=2, test_scenes=1, val_scenes=1, seed=1)
    manifest = json.loads((root / "manifest.json").read_text())
    del manifest["splits"]["test"]
    (root / "manifest.json").write_text(json.dumps(manifest))
    shutil.rmtree(root / "test")
    trainer = Namespace(
        default_root_dir=str(tmp_path / "run"), limit_val_batches=None, check_val_every_n_epoch=1
    )
    model = Namespace(net=Namespace(weights=None), eval=Namespace(output_dir=None))
    cfg = Namespace(
        trainer=trainer, data=Namespace(root=str(root)), model=model, ckpt_path=None, overwrite=False
    )
    check_inputs("fit", cfg)
    for tar in (root / "validation").glob("*.tar"):
        tar.unlink()
    with pytest.raises(UserError, match=f"no shards in {root / 'validation'}"):
        check_inputs("fit", cfg)


@pytest.mark.parametrize(
    "name, expected",
    [
        ("missing", "--ckpt_path {path} does not exist: give RUN/checkpoints/last.ckpt of `aesplat fit`"),
        ("truncated", "checkpoint file {path} is truncated or corrupt (a damaged zip archive); copy it again"),
        ("garbage", "checkpoint file {path} is not a torch file; copy it again or give another file"),
        ("exported", "--ckpt_path {path} is an exported weights file (scripts/export_weights.py), not a "
                     "Lightning checkpoint: give it as --model.net.weights FILE instead"),
    ],
)  # fmt: skip
def test_a_bad_checkpoint_is_named_with_what_it_is(name, expected, checkpoints, shards, capsys, tmp_path):
    path = checkpoints.get(name, tmp_path / "missing.ckpt")
    run_dir = tmp_path / "run"
    code, err = aesplat(capsys, "test", *common(shards, run_dir), "--ckpt_path", str(path))
    line = one_line(err)
    assert code == 1 and line.startswith("aesplat test: " + expected.format(path=path)), line
    assert "weights_only" not in line  # never torch's advice to unpickle a file of unknown origin
    assert not run_dir.exists()


def test_bad_weights_files_stop_before_the_run_starts(checkpoints, shards, capsys, tmp_path):
    run_dir = tmp_path / "run"
    code, err = aesplat(capsys, "fit", *common(shards, run_dir), "--model.net.weights", str(tmp_path / "w.pt"))
    assert code == 1
    assert (
        one_line(err)
        == f"aesplat fit: --model.net.weights file {tmp_path / 'w.pt'} does not exist (or is not a file)"
    )
    code, err = aesplat(
        capsys, "fit", *common(shards, run_dir), "--model.net.weights", str(checkpoints["garbage"])
    )
    assert code == 1 and one_line(err).endswith("is not a torch file; copy it again or give another file")
    # Weights of another network (SH degree 2 into a degree-1 model): the loader's message, on one line.
    code, err = aesplat(capsys, "fit", *common(shards, run_dir), "--model.net.weights",
                        str(checkpoints["exported"]), "--model.net.sh_degree", "1",
                        "--seed_everything", "false")  # fmt: skip
    line = one_line(err, after_start=True)
    assert code == 1 and line.startswith(f"aesplat fit: {checkpoints['exported']}: '") and "has shape" in line
    assert "The checkpoint was trained with model.net {'size': 'tiny'" in line
    assert not run_dir.exists()


def test_fit_refuses_a_folder_holding_a_run(checkpoints, shards, capsys, tmp_path):
    run_dir = checkpoints["last"].parent.parent  # RUN/config.yaml and RUN/checkpoints/last.ckpt
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    code, err = aesplat(capsys, "fit", *common(shards, run_dir))
    assert code == 1 and one_line(err) == (
        f"aesplat fit: {run_dir} already holds a run (config.yaml): resume it with --ckpt_path last, give a "
        "new --trainer.default_root_dir, or --overwrite to delete it and start afresh"
    )
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before  # nothing touched


def test_overwrite_deletes_the_run_dir_but_never_the_working_folder(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "last.ckpt").write_bytes(b"old")
    (run_dir / ".lock").write_text("held by this fit")
    clear_run_dir(run_dir)
    assert [p.name for p in run_dir.iterdir()] == [".lock"]  # the lock stays with the fit that deletes
    monkeypatch.chdir(tmp_path)
    for folder in (tmp_path, tmp_path.parent, Path(".")):
        with pytest.raises(ValueError, match="--overwrite will not delete"):
            clear_run_dir(folder)
    assert tmp_path.is_dir()


def test_a_config_typo_is_one_line_not_the_usage(capsys, shards, tmp_path):
    code, err = aesplat(capsys, "fit", *common(shards, tmp_path / "run"), "--model.net.sizee", "tiny")
    assert code == 2 and one_line(err) == (
        "aesplat fit: model.net: Option 'sizee' is not accepted (`aesplat fit --help` lists the options)"
    )
    code, err = aesplat(capsys, "test", "-c", "conf/smoke.yaml", "--trainer.max_steps", "many")
    assert code == 2 and one_line(err).startswith("aesplat test: trainer.max_steps: Expected a <class 'int'>")
    assert not (tmp_path / "run").exists()


def test_parser_error_line_keeps_the_key_and_the_reason():
    message = "Parser key \"model.net\":\n  Does not validate\n  Errors:\n    Option 'x' is not accepted\n"
    assert parser_error_line(message) == "model.net: Option 'x' is not accepted"
    assert parser_error_line("unrecognized arguments: --foo 3") == "unrecognized arguments: --foo 3"
    assert explicit_keys(["--model.net.size", "small", "--model.eval.output_dir=x", "--data.root", "d"],
                             "model.") == ["model.net.size", "model.eval.output_dir"]  # fmt: skip


def test_the_console_script_prints_one_line_and_debug_shows_the_traceback(tmp_path, monkeypatch):
    args = ["test", "-c", "conf/smoke.yaml", "--data.root", str(tmp_path / "nowhere"),
            "--trainer.default_root_dir", str(tmp_path / "run")]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-m", "aesplat.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 1 and proc.stdout == ""
    assert one_line(proc.stderr).startswith(f"aesplat test: no shards in {tmp_path / 'nowhere'}: the folder")
    monkeypatch.setenv("AESPLAT_DEBUG", "1")  # the error itself, with its traceback
    with pytest.raises(FileNotFoundError, match="does not exist"):
        cli.main(args)
    assert not (tmp_path / "run").exists()


def test_evaluation_folders_are_new_and_the_latest_link_moves(tmp_path, monkeypatch):
    from datetime import datetime, timezone

    from aesplat.train.run_dir import evaluation_dir, point_latest

    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    now = datetime(2026, 11, 24, 15, 0, 0, tzinfo=timezone.utc)
    first = evaluation_dir(tmp_path, "test", now)
    assert first == tmp_path / "test-20261124-150000"
    first.mkdir()
    second = evaluation_dir(tmp_path, "test", now)  # the same second: a new name, never the same folder
    assert second == tmp_path / "test-20261124-150000-2"
    second.mkdir()
    assert point_latest(first).resolve() == first.resolve()
    assert point_latest(second).resolve() == second.resolve()
    assert os.readlink(tmp_path / "test-latest") == second.name  # relative: the run folder can move
    monkeypatch.setenv("SLURM_JOB_ID", "77")
    assert evaluation_dir(tmp_path, "validate") == tmp_path / "validate-job77"


def test_a_value_the_model_refuses_is_one_line(shards, capsys, tmp_path):
    code, err = aesplat(capsys, "fit", *common(shards, tmp_path / "run"), "--model.net.size", "huge",
                        "--seed_everything", "false")  # fmt: skip
    assert code == 1 and one_line(err, after_start=True) == (
        "aesplat fit: invalid configuration: unknown model size 'huge'; choose one of tiny, base, large"
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", ["test", "validate"])
def test_more_targets_than_the_samples_carry_is_refused_before_evaluating(command, shards, checkpoints, capsys,
                                                                          tmp_path):  # fmt: skip
    """The samples carry 3 targets: asking for 5 would skip every one of them as unusable."""
    run_dir = tmp_path / "run"
    extra = ["--data.validate_on_test", "true"] if command == "validate" else []
    code, err = aesplat(capsys, command, *common(shards, run_dir), "--ckpt_path", str(checkpoints["last"]),
                        "--data.eval_num_target_views", "5", *extra)  # fmt: skip
    assert code == 1 and one_line(err) == (
        f"aesplat {command}: data.eval_num_target_views 5: 1 of the 1 samples of the test shards in {shards} "
        "carry fewer targets (from 3 to 3); give at most 3, or leave it unset to evaluate every target"
    )
    assert not run_dir.exists()
    code, err = aesplat(capsys, command, *common(shards, run_dir), "--ckpt_path", str(checkpoints["last"]),
                        "--data.eval_num_target_views", "0", *extra)  # fmt: skip
    assert code == 1 and one_line(err) == (
        f"aesplat {command}: invalid configuration: data.eval_num_target_views = 0: it must be 1 or more (or "
        "unset: every target)"
    )
    assert not run_dir.exists()


def test_an_evaluation_of_nothing_fails_and_points_no_latest_link(shards, checkpoints, tmp_path):
    """Shards whose manifest does not count the targets: every sample is skipped while evaluating, and the
    command must say so and fail, never exit 0 with an empty summary behind ``test-latest``."""
    root = tmp_path / "shards"
    shutil.copytree(shards, root)
    manifest = json.loads((root / "manifest.json").read_text())
    del manifest["splits"]["test"]["evaluation_samples"]
    (root / "manifest.json").write_text(json.dumps(manifest))
    run_dir = tmp_path / "run"
    args = ["test", *common(root, run_dir), "--ckpt_path", str(checkpoints["last"]),
            "--data.eval_num_target_views", "5"]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-m", "aesplat.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    code, err = proc.returncode, proc.stderr
    lines = [line for line in err.splitlines() if line.startswith("aesplat test:")]
    assert code == 1 and "Traceback" not in err, err
    assert lines == ["aesplat test: evaluated no scene: every sample was skipped (too_few_targets: 1); see the "
                     "warnings above for each sample's reason"]  # fmt: skip
    assert not (run_dir / "test-latest").exists() and not list(run_dir.glob("test-*/summary.json"))


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--data.train_batches_per_epoch", "0"], "data.train_batches_per_epoch = 0: it must be 1 or more "
         "batches"),
        (["--data.seed=-1"], "data.seed = -1: it must be a seed of 0 or more"),
        (["--data.eval_num_target_views", "0"], "data.eval_num_target_views = 0: it must be 1 or more (or "
         "unset: every target)"),
        (["--trainer.accumulate_grad_batches", "2"], "trainer.accumulate_grad_batches = 2: it must be 1: the "
         "module steps its optimizer itself once per batch; raise data.batch_size instead"),
        (["--trainer.val_check_interval", "0"], "trainer.val_check_interval = 0: it must be 1 or more steps, "
         "or a fraction of an epoch in (0, 1]"),
        (["--trainer.log_every_n_steps", "0"], "trainer.log_every_n_steps = 0: it must be 1 or more steps"),
    ],
)  # fmt: skip
def test_values_that_failed_after_the_model_was_built_are_one_line(shards, capsys, tmp_path, flags, message):
    """Each of these once stopped with a traceback from Lightning or a data-loader worker."""
    run = tmp_path / "run"
    code, err = aesplat(capsys, "fit", *common(shards, run), *flags)
    assert code == 1 and one_line(err, after_start=True) == f"aesplat fit: invalid configuration: {message}"
    assert not run.exists()


def test_a_trainer_value_lightning_refuses_is_one_line(shards, tmp_path):
    """Lightning's own refusal (here: zero devices) is the one line, not its traceback (a fresh process: its
    log handlers are its own)."""
    run = tmp_path / "run"
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore"}
    args = ["fit", *common(shards, run), "--trainer.devices", "0", "--seed_everything", "false"]
    proc = subprocess.run([sys.executable, "-m", "aesplat.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 1 and one_line(proc.stderr, after_start=True) == (
        "aesplat fit: invalid configuration: trainer: `Trainer(devices='0')` value is not a valid input using "
        "cpu accelerator."
    )
    assert not run.exists()
