"""`aesplat fit|validate|test` as a hostile or careless user meets them: a checkpoint never names a class,
`last` behaves as an explicit path, --overwrite never deletes the run's inputs, one fit at a time per run
folder, values out of range and broken YAML are one line before anything is written, a fit that fails before
its first checkpoint leaves nothing behind, and a fit stopped by a signal saves and exits with 128 + it.
"""

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from aesplat import cli
from aesplat.lightning_cli import run_lightning
from aesplat.train import AESplatModule
from tests.helpers import REPO, aesplat, common, one_line, tree, write_tiny_checkpoint
from tests.train.helpers import hold_lock

pytestmark = pytest.mark.filterwarnings("ignore")


@pytest.fixture
def run(tmp_path) -> Path:
    """A run folder as `aesplat fit` leaves it: RUN/checkpoints/last.ckpt, RUN/config.yaml."""
    write_tiny_checkpoint(tmp_path / "run")
    return tmp_path / "run"


def test_a_checkpoint_naming_a_class_never_instantiates_it(run, shards, capsys, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    crafted = {"class_path": "logging.FileHandler", "init_args": {"filename": str(victim), "mode": "w"}}
    ckpt["hyper_parameters"]["net"]["options"] = {"x": crafted}  # opening the handler truncates the file
    torch.save(ckpt, run / "checkpoints" / "last.ckpt")
    before = tree(run)
    for command, path in (("test", str(run / "checkpoints" / "last.ckpt")), ("validate", "last"),
                          ("fit", "last")):  # fmt: skip
        code, err = aesplat(capsys, command, *common(shards, run), "--ckpt_path", path)
        assert code == 1 and one_line(err).startswith(f"aesplat {command}: checkpoint {run / 'checkpoints'}")
        assert "name a class to instantiate (net.options.x.class_path)" in err
    assert victim.read_text() == "precious\n" and tree(run) == before


def test_last_is_checked_as_an_explicit_path_is(run, shards, capsys):
    """`--ckpt_path last` goes through the same checkpoint check and names the --model.* flags the checkpoint
    overrides; a damaged newest file is skipped, and said so."""
    last = run / "checkpoints" / "last.ckpt"
    (run / "hpc_ckpt_1.ckpt").write_bytes(last.read_bytes())
    last.write_bytes(last.read_bytes()[:4096])  # a save cut short
    cli.main(["test", *common(shards, run), "--ckpt_path", "last", "--model.net.sh_degree", "1",
              "--model.net.near", "0.5", "--trainer.limit_test_batches", "1"])  # fmt: skip
    out = capsys.readouterr()
    assert f"aesplat test: checkpoint file {last} is truncated or corrupt" in out.err and "; skipped" in out.err
    assert f"--ckpt_path last: {run / 'hpc_ckpt_1.ckpt'} (step 0), the newest that loads" in out.out
    for flag, value, saved in (("sh_degree", 1, 2), ("near", 0.5, 0.1)):
        assert (f"aesplat test: --model.net.{flag} {value} has no effect: the checkpoint "
                f"{run / 'hpc_ckpt_1.ckpt'} sets it to {saved}") in out.err  # fmt: skip


def test_overwrite_never_deletes_an_input_inside_the_run_folder(shards, capsys, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"a run")
    weights = run / "weights.pt"
    torch.save({"w": torch.zeros(1)}, weights)
    inside = run / "data"
    os.symlink(shards, inside)  # the data root reached through the run folder
    before = tree(run)
    for flags, named in ((["--data.root", str(inside)], "--data.root"),
                         (["--model.net.weights", str(weights)], "--model.net.weights")):  # fmt: skip
        argv = [*common(shards, run), *flags, "--overwrite"]
        code, err = aesplat(capsys, "fit", *argv)
        assert code == 1 and f"--overwrite will not delete {run}: it holds {named}" in one_line(err)
    assert tree(run) == before


def test_a_second_resume_of_a_run_in_training_is_refused(run, shards, capsys):
    holder, conn = hold_lock(run)
    try:
        before = tree(run)
        code, err = aesplat(capsys, "fit", *common(shards, run), "--ckpt_path", "last")
        line = one_line(err, after_start=True)
        assert code == 1 and line.startswith(f"aesplat fit: {run.resolve()} is in use: aesplat fit (pid "), line
        assert tree(run) == before
    finally:
        conn.send_bytes(b"done")
        holder.join(timeout=60)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--model.optim.lr=-1e-4"], "model.optim.lr = -0.0001: it must be a positive learning rate"),
        (["--model.net.sh_degree", "7"], "model.net.sh_degree = 7: it must be an SH degree in 0..4"),
        (["--data.image_size", "30"], "data.image_size = 30: it must be a multiple of the patch size 14"),
        (["--trainer.max_steps", "0"], "trainer.max_steps = 0: it must be -1 (no limit) or 1 or more steps"),
        (["--model.net.far", "0.01"], "model.net.far = 0.01: it must be more than model.net.near (0.1)"),
        (["--model.loss.lpips_weight=-1"], "model.loss.lpips_weight = -1.0: it must be a weight of 0"),
        (["--model.net.options.patch_size", "0"], "model.net.options.patch_size = 0: it must be a patch side"),
        (["--model.render.options.tile_size", "0"], "tile_size, chunk and max_elements must be positive"),
        (["--model.optim.impl", "magic"], "unknown optim.impl 'magic'"),
        (["--distributed.timeout", "0.05"], "distributed.timeout = 0.05: it must be 10 to 604800 seconds"),
        (["--distributed.timeout", "1e18"], "distributed.timeout = 1e+18: it must be 10 to 604800 seconds"),
    ],
)
def test_values_out_of_range_stop_before_anything_is_written(shards, capsys, tmp_path, flags, message):
    run = tmp_path / "run"
    code, err = aesplat(capsys, "fit", *common(shards, run), *flags)
    line = one_line(err)
    assert code == 1 and line.startswith("aesplat fit: invalid configuration: ") and message in line, line
    assert not run.exists()


def test_a_config_file_that_is_not_yaml_is_one_line(shards, capsys, tmp_path):
    tabbed = tmp_path / "tabbed.yaml"
    tabbed.write_text("model:\n\tnet:\n    size: tiny\n")
    code, err = aesplat(capsys, "fit", *common(shards, tmp_path / "run"), "-c", str(tabbed))
    assert code == 1 and one_line(err) == (
        f"aesplat fit: -c {tabbed} is not valid YAML at line 2, column 1 (found character '\\t' that cannot "
        "start any token): indent with spaces, YAML does not allow tabs"
    )
    listed = tmp_path / "list.yaml"
    listed.write_text("- trainer\n- model\n")
    code, err = aesplat(capsys, "test", "-c", str(listed))
    assert code == 1 and one_line(err) == (
        f"aesplat test: -c {listed} holds a list, not a mapping of sections (trainer:, model:, data:, ...)"
    )
    assert not (tmp_path / "run").exists()


class FailsAtTheFirstStep(AESplatModule):
    def training_step(self, batch, batch_idx):
        raise RuntimeError("the first step failed")


def test_a_fit_that_fails_before_its_first_checkpoint_leaves_nothing(shards, capsys, tmp_path):
    run = tmp_path / "run"
    argv = ["fit", *common(shards, run), "--seed_everything", "false"]
    with pytest.raises(RuntimeError, match="the first step failed"):
        run_lightning(argv, module_class=FailsAtTheFirstStep)
    assert f"nothing was trained: removed config.yaml from {run}, so the corrected" in capsys.readouterr().err
    assert not run.exists()  # so the corrected command is not refused as "already holds a run"


def test_a_fit_stopped_by_sigterm_saves_where_it_stopped_and_exits_143(shards, capsys, tmp_path):
    run = tmp_path / "run"
    overlay = tmp_path / "stop.yaml"
    overlay.write_text(
        "trainer:\n  callbacks:\n    - class_path: tests.train.helpers.SignalDuringStep\n"
        f"      init_args:\n        at: 1\n        signum: {int(signal.SIGTERM)}\n"
    )
    code, err = aesplat(capsys, "fit", *common(shards, run), "-c", str(overlay), "--trainer.max_steps", "50",
                        "--last_checkpoint.every_n_train_steps", "40")  # fmt: skip
    last = run / "checkpoints" / "last.ckpt"
    assert code == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == (
        f"aesplat fit: stopped by SIGTERM after step 2; saved {last}: resume with --ckpt_path last"
    )
    assert torch.load(last, weights_only=True)["global_step"] == 2


def start_fit_held(data: Path, tmp_path: Path, launch: list[str], validation: bool = False,
                   wandb: bool = False):  # fmt: skip
    """`aesplat fit` with two data-loader workers, in a process group of its own, behind the ``launch``
    command (``timeout ...`` or nothing); it holds in step 2 (with ``validation``: in the validation after step
    4) until it has a stop signal; with ``wandb``, logging to an offline wandb run. Returns the process, the
    run folder and its stderr's file, once the fit holds there."""
    run, ready, err = tmp_path / "run", tmp_path / "ready", tmp_path / "stderr"
    overlay = tmp_path / "hold.yaml"
    overlay.write_text(
        "trainer:\n  callbacks:\n    - class_path: tests.train.helpers.HoldUntilStopSignal\n"
        f"      init_args:\n        ready: {ready}\n        at: {0 if validation else 1}\n"
        f"        validation: {str(validation).lower()}\n"
    )
    argv = [sys.executable, "-m", "aesplat.cli", "fit", *common(data, run), "-c", str(overlay),
            "--data.num_workers", "2", "--trainer.max_steps", "50", "--last_checkpoint.every_n_train_steps",
            "40", "--trainer.enable_progress_bar", "false"]  # fmt: skip
    if wandb:
        argv += ["--trainer.logger", "true", "--wandb.mode", "offline"]
    env = {**os.environ, "WANDB_MODE": "offline" if wandb else "disabled", "PYTHONWARNINGS": "ignore"}
    with open(err, "w") as stderr:
        proc = subprocess.Popen([*launch, *argv], cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=stderr,
                                start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + 600
    while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    if not ready.exists():
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        pytest.fail(f"the fit never reached the step it holds in:\n{err.read_text()[-4000:]}")
    return proc, run, err


def group_members(pgid: int) -> list[str]:
    """The processes (pid and command) still in process group ``pgid``, read from /proc."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid and fields[0] != "Z":
                found.append(f"{stat.parent.name} {(stat.parent / 'cmdline').read_bytes()[:80]!r}")
    return found


def assert_stopped_and_saved(proc, run: Path, err: Path, step: int) -> None:
    """The fit exited 143, saying where it stopped, and its last.ckpt holds that step; no process of its group
    is left."""
    try:
        code = proc.wait(timeout=600)
        left = group_members(proc.pid)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert not left, f"processes of the fit left running: {left}"
    last = run / "checkpoints" / "last.ckpt"
    text = err.read_text()
    assert code == 128 + signal.SIGTERM, text[-4000:]
    assert "killed by signal" not in text and "Traceback" not in text, text[-4000:]
    assert text.strip().splitlines()[-1] == (
        f"aesplat fit: stopped by SIGTERM after step {step}; saved {last}: resume with --ckpt_path last"
    )
    assert torch.load(last, weights_only=True)["global_step"] == step


@pytest.mark.parametrize("validation", [False, True], ids=["training", "validation"])
def test_sigterm_to_the_whole_process_group_saves_and_exits_143(shards, tmp_path, validation):
    """What `kill -TERM -PGID`, systemd and SLURM do: every process of the run gets the signal, the data-loader
    workers (of training and of validation) too. They must outlive it, for the step under way to finish."""
    proc, run, err = start_fit_held(shards, tmp_path, [], validation)
    os.killpg(proc.pid, signal.SIGTERM)
    assert_stopped_and_saved(proc, run, err, step=4 if validation else 2)


def test_a_time_limit_of_timeout_saves_and_exits_143(shards, tmp_path):
    """`timeout -s TERM N aesplat fit ...` sends SIGTERM to its whole process group when the time is up
    (`--preserve-status`: its own status is then the fit's, not 124). The time is up when the fit holds in step
    2: the test sends `timeout` the SIGALRM by which its own timer tells it so."""
    if shutil.which("timeout") is None:
        pytest.skip("no `timeout` command (GNU coreutils) here")
    proc, run, err = start_fit_held(shards, tmp_path, ["timeout", "--preserve-status", "-s", "TERM", "3600"])
    os.kill(proc.pid, signal.SIGALRM)
    assert_stopped_and_saved(proc, run, err, step=2)


def test_sigterm_to_every_process_of_a_job_wandb_included_saves_and_exits_143(shards, tmp_path):
    """What `scancel` and a SLURM time limit do to a job that logs to wandb: SIGTERM reaches wandb's service
    process too (it runs in a session of its own, so a process group signal misses it; a job's does not). The
    next log then fails; that once stopped the fit in the middle of the step, with nothing saved."""
    proc, run, err = start_fit_held(shards, tmp_path, [], wandb=True)
    stats = Path("/proc").glob("[0-9]*/stat")
    service = [p.parent.name for p in stats if _parent_and_name(p) == (proc.pid, True)]
    assert service, "the fit started no wandb service process"
    for pid in service:
        os.kill(int(pid), signal.SIGTERM)
    os.killpg(proc.pid, signal.SIGTERM)
    assert_stopped_and_saved(proc, run, err, step=2)
    lines = err.read_text().splitlines()
    assert any(line.startswith("aesplat fit: wandb stopped taking this run's logs (") for line in lines)


def _parent_and_name(stat: Path) -> tuple[int, bool] | None:
    """(parent pid, whether the process is wandb's) from a /proc/PID/stat file; None once it is gone."""
    with contextlib.suppress(OSError, IndexError, ValueError):
        name, rest = stat.read_text().split("(", 1)[1].rsplit(")", 1)
        return int(rest.split()[1]), name.startswith("wandb")
    return None
