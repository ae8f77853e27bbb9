"""The `aesplat` command: fit + test end to end on the CPU, config printing, every shipped config, dispatch."""

import csv
import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from aesplat import cli
from tests.helpers import REPO, make_shards


def aesplat_command() -> list[str]:
    script = Path(sys.executable).parent / "aesplat"
    return [str(script)] if script.exists() else [sys.executable, "-m", "aesplat.cli"]


def run_aesplat(*args: str, timeout: int = 400) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([*aesplat_command(), *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip
    assert proc.returncode == 0, (
        f"aesplat {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}"
    )
    return proc


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    """Two test scenes here, not the suite's one."""
    return make_shards(tmp_path_factory.mktemp("cli_data"), scenes=2, test_scenes=2, seed=1)


def test_smoke_fit_then_test_writes_checkpoint_csv_and_json(shards, tmp_path):
    run_dir = tmp_path / "run"
    common = ["-c", "conf/smoke.yaml", "--data.root", str(shards), "--trainer.default_root_dir", str(run_dir)]
    run_aesplat("fit", *common)
    last = run_dir / "checkpoints" / "last.ckpt"
    assert last.exists() and list((run_dir / "checkpoints").glob("best-step*.ckpt"))
    ckpt = torch.load(last, weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 4
    assert (run_dir / "config.yaml").exists() and (run_dir / "wandb_run_id").exists()
    config = (run_dir / "config.yaml").read_text()

    # The test writes its config and results into a folder of its own, and names the flag the checkpoint
    # overrides; the training run's config stays as it was (predict reads the image size from it).
    proc = run_aesplat("test", *common, "--ckpt_path", str(last), "--data.image_size", "42",
                       "--model.net.sh_degree", "1")  # fmt: skip
    assert "--model.net.sh_degree 1 has no effect: the checkpoint" in proc.stderr
    assert (run_dir / "config.yaml").read_text() == config
    out = run_dir / "test-latest"
    assert out.is_symlink() and out.resolve().parent == run_dir.resolve()
    assert out.resolve().name.startswith("test-20") and "image_size: 42" in (out / "config.yaml").read_text()
    with open(out / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(float(r["psnr"]) > 5 for r in rows)
    # The test shards carry highlight masks (synthetic scenes): PSNR on the rest is always there, and equals
    # the whole image's where a scene has no highlight pixel.
    assert all(r["psnr_rest"] != "" and r["highlight_fraction"] != "" for r in rows)
    for r in rows:
        if float(r["highlight_fraction"]) == 0:
            assert r["psnr_highlight"] == ""
            assert float(r["psnr_rest"]) == pytest.approx(float(r["psnr"]), rel=1e-4)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_scenes"] == 2
    assert set(summary["buckets"]) >= {"small", "medium", "large"}
    assert summary["metrics"]["lpips"] is None and "lpips" in summary["unavailable"]
    assert len(list((out / "renders").glob("*.png"))) == 2
    # Point lattice or scene: the shares and the fusion gain per scene; the transfer gain needs larger shards.
    assert all(0 <= float(r[m]) <= 1 for r in rows for m in ("opaque_share", "subpixel_share"))
    assert all(math.isfinite(float(r["fusion_gain_db"])) and r["transfer_gain_db"] == "" for r in rows)
    assert summary["metrics"]["transfer_gain_db"] is None and summary["counts"]["fusion_gain_db"] == 2

    # `--ckpt_path last` continues the run from its directory (one more epoch), with the same wandb id.
    run_id = (run_dir / "wandb_run_id").read_text()
    run_aesplat("fit", *common, "--trainer.max_steps", "8", "--ckpt_path", "last")
    assert torch.load(last, weights_only=True, map_location="cpu")["global_step"] == 8
    assert (run_dir / "wandb_run_id").read_text() == run_id


def print_config(capsys, *args: str) -> str:
    with pytest.raises(SystemExit) as info:
        cli.main([*args, "--print_config"])
    assert info.value.code in (0, None)
    return capsys.readouterr().out


def test_print_config_applies_overlays_and_dotted_overrides(capsys):
    text = print_config(capsys, "fit", "-c", "conf/smoke.yaml", "--model.loss.lpips_weight", "0.2",
                        "--trainer.max_steps", "7")  # fmt: skip
    assert "lpips_weight: 0.2" in text and "max_steps: 7" in text
    assert "cameras: predicted" in text  # the method (pose-free) is the default


def test_posed_fit_saves_loads_and_tests_through_plain_test(shards, tmp_path):
    """`--model.cameras dataset` trains with the data set's cameras, the checkpoint and the run's config say
    so, and a plain `aesplat test` of that checkpoint evaluates it with the data set's cameras too."""
    run_dir = tmp_path / "posed"
    common = ["-c", "conf/smoke.yaml", "--data.root", str(shards), "--trainer.default_root_dir", str(run_dir)]
    run_aesplat("fit", *common, "--model.cameras", "dataset", "--trainer.max_steps", "2",
                "--last_checkpoint.every_n_train_steps", "2")  # fmt: skip
    last = run_dir / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=True, map_location="cpu")["hyper_parameters"]["cameras"] == "dataset"
    assert "cameras: dataset" in (run_dir / "config.yaml").read_text()

    run_aesplat("test", *common, "--ckpt_path", str(last))  # the config says predicted; the checkpoint wins
    summary = json.loads((run_dir / "test-latest" / "summary.json").read_text())
    assert summary["cameras"] == "dataset" and summary["num_scenes"] == 2 and summary["metrics"]["psnr"] > 5
    assert summary["metrics"]["rot_err_deg"] is None  # no pose was predicted, so none is scored


def test_each_command_runs_the_main_of_its_module(monkeypatch):
    """`aesplat NAME ARGS` calls ``main(ARGS)`` of NAME's module (fakes stand in for the modules)."""
    modules = {"predict": "aesplat.predict", "bench": "aesplat.bench.command",
               "export": "aesplat.export.command", "view": "aesplat.view.command"}  # fmt: skip
    assert {name: module for name, (module, _) in cli.COMMANDS.items()} == modules
    calls = []
    for name, module in modules.items():
        fake = types.ModuleType(module)
        fake.main = lambda argv, name=name: calls.append((name, list(argv)))
        monkeypatch.setitem(sys.modules, module, fake)
    for name in modules:
        cli.main([name, "--ckpt", "a.ckpt", "x.png"])
    assert calls == [(name, ["--ckpt", "a.ckpt", "x.png"]) for name in modules]


def test_help_lists_the_commands_then_the_lightning_options(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code in (0, None)
    lines = capsys.readouterr().out.splitlines()
    assert lines[:6] == [
        "aesplat fit|validate|test -c CONFIG.yaml [--key value ...]  train / evaluate (LightningCLI)",
        "aesplat predict --help                    images -> Gaussians, cameras, renders",
        "aesplat bench --help                      accuracy-versus-time report",
        "aesplat export --help                     a prediction for COLMAP, nerfstudio, web viewers",
        "aesplat view --help                       a prediction in the browser",
        "",
    ]
    assert lines[6].startswith("usage: ") and "{fit,validate,test}" in lines[6]
