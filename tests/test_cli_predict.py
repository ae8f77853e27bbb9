"""`aesplat predict` as a careless or unlucky user meets it: --overwrite never deletes what the command reads or
where the user stands, a SIGTERM leaves no staging folder, every bad option is one line, and a checkpoint
that does not say its image size is refused rather than guessed."""

import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.predict import main
from tests.helpers import REPO, write_tiny_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("run"))


def photos(folder: Path, n: int = 2) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        path = folder / f"{i}.png"
        Image.fromarray(np.full((28, 28, 3), 40 * i + 20, np.uint8)).save(path)
        paths.append(str(path))
    return paths


def predict(capsys, *args: str) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main(list(args))
    code, err = info.value.code, capsys.readouterr().err
    if isinstance(code, str):
        return 1, code
    return code, err.strip()


def test_overwrite_never_deletes_a_folder_holding_the_inputs_or_the_current_folder(ckpt, tmp_path, capsys,
                                                                                   monkeypatch):  # fmt: skip
    out = tmp_path / "out"
    images = photos(out / "photos")  # the photos live inside the folder --overwrite would replace
    args = ["--ckpt", str(ckpt), "--out", str(out), "--overwrite", "--no-progress", *images]
    code, line = predict(capsys, *args)
    assert code == 1 and line.startswith(
        f"aesplat predict: --overwrite will not delete {out}: it holds the input"
    )
    assert sorted(p.name for p in (out / "photos").iterdir()) == ["0.png", "1.png"]

    elsewhere = photos(tmp_path / "elsewhere")
    (out / "notes.txt").write_text("the user's")
    monkeypatch.chdir(out / "photos")  # the user stands inside it
    code, line = predict(capsys, "--ckpt", str(ckpt), "--out", str(out), "--overwrite", *elsewhere)
    assert code == 1 and "it holds the current folder" in line
    monkeypatch.chdir(tmp_path)
    ckpt_inside = out / "model.ckpt"
    shutil.copy(ckpt, ckpt_inside)
    code, line = predict(capsys, "--ckpt", str(ckpt_inside), "--out", str(out), "--overwrite", *elsewhere)
    assert code == 1 and "it holds --ckpt" in line
    assert (out / "notes.txt").read_text() == "the user's"
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)  # an empty --out is replaced as a whole too: never the folder the user is in
    code, line = predict(capsys, "--ckpt", str(ckpt), "--out", ".", *elsewhere)
    assert (
        code == 1
        and line
        == f"aesplat predict: --out will not delete {empty}: it holds the current folder; "
        "give a folder of its own"
    )
    assert empty.is_dir()


STOPPED = textwrap.dedent(
    """
    import os, signal, sys
    from aesplat import predict

    def killed_while_writing(*args, **kwargs):  # SIGTERM arrives while the outputs are being written
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM must stop the command")

    predict.write_ply = killed_while_writing
    predict.main(sys.argv[1:])
    """
)


def test_sigterm_leaves_no_staging_folder_and_exits_143(ckpt, tmp_path):
    out = tmp_path / "out"
    args = [
        "--ckpt",
        str(ckpt),
        "--out",
        str(out),
        "--novel-frames",
        "2",
        "--no-progress",
        *photos(tmp_path / "in"),
    ]
    proc = subprocess.run([sys.executable, "-c", STOPPED, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})  # fmt: skip
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "aesplat predict: stopped by SIGTERM"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]  # neither out nor its hidden staging folder


@pytest.mark.parametrize(
    "option, code, message",
    [
        (["--size", "0"], 1, "--size must be a positive number of pixels, got 0"),
        (["--min-opacity", "1.5"], 1, "--min-opacity must be in [0, 1), got 1.5"),
        (["--ply-sh-degree", "-1"], 1, "--ply-sh-degree must be 0 or more, got -1"),
        (["--backend", "vulkan"], 1, "--backend vulkan is not a renderer: give auto, torch, gsplat"),
        (["--device", "tpu:0"], 1, "--device tpu:0 is not a device: give cpu, cuda, cuda:1, ... or auto"),
        (["--novel-frames", "many"], 2, "argument --novel-frames: invalid int value: 'many'"),
    ],
)
def test_every_bad_option_is_one_line(ckpt, tmp_path, capsys, option, code, message):
    args = ["--ckpt", str(ckpt), "--out", str(tmp_path / "out"), *photos(tmp_path / "in"), *option]
    got, line = predict(capsys, *args)
    assert got == code and "\n" not in line and message in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_the_image_size_is_never_guessed(ckpt, tmp_path, capsys):
    """A checkpoint copied out of its run folder: its own record gives the size; without one, a clear line
    asks for --size (it once fell back to 224 px without a word)."""
    bare = tmp_path / "bare.ckpt"
    shutil.copy(ckpt, bare)  # no config.yaml beside it, no size recorded in it
    images = photos(tmp_path / "in")
    code, line = predict(capsys, "--ckpt", str(bare), "--out", str(tmp_path / "out"), *images)
    assert code == 1 and line == (
        f"aesplat predict: {bare} does not say which image size it was trained at (it is not in its run "
        "folder beside the run's config.yaml): give --size, the run's data.image_size"
    )
    recorded = tmp_path / "recorded.ckpt"
    torch.save({**torch.load(ckpt, weights_only=True), "aesplat_data": {"image_size": 42}}, recorded)
    assert main(["--ckpt", str(recorded), "--out", str(tmp_path / "out"), "--novel-frames", "2",
                 "--no-progress", *images]) == 0  # fmt: skip
    assert Image.open(tmp_path / "out" / "inputs" / "00_0.png").size == (42, 42)


def test_a_config_yaml_that_cannot_be_used_is_named_in_one_line_and_never_runs(ckpt, tmp_path, capsys):
    """The run's config.yaml is data: a Python tag constructs nothing, and a file YAML cannot parse is named.
    Without a size in the checkpoint the one line says why the file did not give it; with one, the file is
    ignored with a line and the prediction goes on."""
    run = tmp_path / "run"
    shutil.copytree(ckpt.parent.parent, run)
    last, config = run / "checkpoints" / "last.ckpt", run / "config.yaml"
    marker = tmp_path / "ran"
    config.write_text(f'data: !!python/object/apply:os.system ["touch {marker}"]\n')
    images = photos(tmp_path / "in")
    code, line = predict(capsys, "--ckpt", str(last), "--out", str(tmp_path / "out"), *images)
    assert code == 1 and line == (
        f"aesplat predict: {last} does not say which image size it was trained at ({config} is ignored: not "
        "YAML this program reads (could not determine a constructor for the tag "
        "'tag:yaml.org,2002:python/object/apply:os.system' at line 1)): give --size, the run's data.image_size"
    )
    assert not marker.exists() and not (tmp_path / "out").exists()

    config.write_text("data: [1, 2\n")  # cut short
    torch.save({**torch.load(last, weights_only=True), "aesplat_data": {"image_size": 28}}, last)
    code = main(["--ckpt", str(last), "--out", str(tmp_path / "out"), "--novel-frames", "2", "--no-progress",
                 *images])  # fmt: skip
    err = capsys.readouterr().err
    why = "not YAML this program reads (did not find expected ',' or ']' at line 2)"
    ignored = f"aesplat: {config} is ignored: {why}"
    assert code == 0 and err.splitlines() == [ignored]
    assert Image.open(tmp_path / "out" / "inputs" / "00_0.png").size == (28, 28)


def test_a_photo_name_too_long_for_the_outputs_is_one_line_before_the_model_loads(ckpt, tmp_path, capsys):
    """``inputs/NN_NAME.png`` adds 7 bytes to the photo's name: a name near the file system's limit once
    failed only after the prediction, writing its outputs."""
    images = photos(tmp_path / "in")
    long = tmp_path / "in" / ("x" * 250 + ".png")
    Path(images[1]).rename(long)
    code, line = predict(capsys, "--ckpt", str(ckpt), "--out", str(tmp_path / "out"), images[0], str(long))
    assert code == 1 and line == (
        f"aesplat predict: the input image {str(long)!r} makes a 257-byte file name under --out (this file "
        "system allows 255); rename the photo"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_a_later_run_removes_the_staging_folder_of_a_run_killed_outright(tmp_path, capsys):
    from aesplat.files import _staging_prefix, written_whole

    out = tmp_path / "out"
    gone = subprocess.run(["sh", "-c", "echo $$"], capture_output=True, text=True)  # a process that has ended
    killed = tmp_path / f"{_staging_prefix(out, int(gone.stdout))}-abc123"  # what kill -9 leaves
    running = tmp_path / f"{_staging_prefix(out, os.getppid())}-def456"  # a run still at work
    elsewhere = tmp_path / f".out.partial-another-host-{gone.stdout.strip()}-0a1b2c"  # a shared file system
    for folder in (killed, running, elsewhere):
        (folder / "gaussians").mkdir(parents=True)
    with written_whole(out, False, "aesplat predict") as staging:
        assert staging.parent.name.startswith(_staging_prefix(out, os.getpid()) + "-")
        staging.mkdir()
        (staging / "cameras.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", running.name, elsewhere.name])
    assert (out / "cameras.json").read_text() == "{}"
    assert capsys.readouterr().out.strip() == (
        f"aesplat predict: removed {killed}, the staging folder of an earlier run that was killed"
    )
