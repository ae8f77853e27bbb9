"""benchmarks/bench_train_step.py: config overrides, recorded loss curves and their comparison."""

import csv
import json
import math
import os
import subprocess
import sys

import pytest
import torch

from tests.helpers import REPO
from tests.script_loader import load_benchmark

SMOKE = str(REPO / "conf" / "smoke.yaml")


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_train_step")


def test_overrides_set_nested_keys_and_leave_the_config_alone(bench):
    cfg = {"model": {"net": {"size": "tiny", "compile": "blocks"}, "optim": {"lr": 1e-4}}}
    out = bench.apply_overrides(
        cfg, ["model.net.compile=none", "model.optim.lr=1e-2", "data.gap_final=[2, 8]", "model.new.x=true"]
    )
    assert out["model"]["net"] == {"size": "tiny", "compile": "none"}
    assert out["model"]["optim"]["lr"] == 0.01  # YAML 1.1 reads 1e-2 as a string; the override reads a number
    assert out["data"]["gap_final"] == [2, 8]
    assert out["model"]["new"] == {"x": True}
    assert cfg == {"model": {"net": {"size": "tiny", "compile": "blocks"}, "optim": {"lr": 1e-4}}}


@pytest.mark.parametrize("bad", ["model.net.compile", "=none", "model..compile=none", "model.net.size.x=1"])
def test_bad_overrides_say_what_is_wrong(bench, bad):
    with pytest.raises(SystemExit, match="--set"):
        bench.apply_overrides({"model": {"net": {"size": "tiny"}}}, [bad])


def test_compare_losses(bench):
    ref = {0: 1.0, 1: 2.0, 2: 4.0, 3: 4.0}
    same = bench.compare_losses(dict(ref), ref, window=2)
    assert same["max relative difference, per step"] == 0
    assert same["max relative difference, 2-step means"] == 0
    ours = {0: 1.1, 1: 2.0, 2: 4.0, 3: 2.0, 4: 9.0}  # step 4 has no partner and is left out
    out = bench.compare_losses(ours, ref, window=2)
    assert out["steps"] == 4 and out["windows"] == 2
    assert math.isclose(out["max relative difference, per step"], 0.5)
    assert math.isclose(out["median relative difference, per step"], 0.05)
    assert math.isclose(out["max relative difference, 2-step means"], 1.0 / 4.0)  # (4 + 2) / 2 = 3 vs 4
    assert out["last window mean loss, this run"] == 3.0 and out["last window mean loss, reference"] == 4.0
    nan = bench.compare_losses({0: math.nan, 1: 2.0}, {0: 1.0, 1: 2.0}, window=2)
    assert nan["non-finite steps"] == 1 and nan["max relative difference, per step"] == 0
    with pytest.raises(SystemExit, match="share no step"):
        bench.compare_losses({5: 1.0}, ref, window=2)


def _run(bench, monkeypatch, capsys, *args):
    monkeypatch.setattr(
        sys, "argv", ["bench_train_step.py", "-c", SMOKE, "--steps", "3", "--warmup", "1", *args]
    )
    bench.main()
    return capsys.readouterr().out


def test_recorded_losses_repeat_with_the_seed_and_change_without_it(bench, monkeypatch, capsys, tmp_path):
    """The same seed gives the same losses (for-loop and foreach AdamW are bit-identical on the CPU); another
    seed gives other weights and batches. The table and the recorded CSV agree on the step count."""
    ref = tmp_path / "ref.csv"
    figures = tmp_path / "figures" / "step.json"
    out = _run(bench, monkeypatch, capsys, "--set", "model.optim.impl=for_loop", "--losses", str(ref), "--json",
               str(figures))  # fmt: skip
    assert "| seconds per step (median) |" in out and "--set model.optim.impl=for_loop" in out
    saved = json.loads(figures.read_text())  # the figures the table prints
    assert f"| seconds per step (median) | {saved['seconds_per_step']:.3f} |" in out
    assert saved["overrides"] == ["model.optim.impl=for_loop"] and saved["steps"] == 3
    assert 0 < saved["rss_before_fit_gib"] <= saved["peak_memory_gib"] and set(saved["stages_ms"]) == set(
        bench.STAGES
    )
    recorded = bench.read_losses(ref)
    assert sorted(recorded) == [0, 1, 2, 3] and all(math.isfinite(v) for v in recorded.values())

    out = _run(bench, monkeypatch, capsys, "--set", "model.optim.impl=foreach", "--compare", str(ref))
    assert "| max relative difference, per step | 0 |" in out

    out = _run(bench, monkeypatch, capsys, "--seed", "1", "--compare", str(ref), "--window", "2")
    row = next(line for line in out.splitlines() if line.startswith("| max relative difference, per step"))
    assert float(row.split("|")[2]) > 1e-3


def test_a_missing_reference_is_reported_before_any_work(bench, monkeypatch, capsys, tmp_path):
    with pytest.raises(SystemExit, match="no such file"):
        _run(bench, monkeypatch, capsys, "--compare", str(tmp_path / "absent.csv"))


def _suite(tmp_path, *parts, **env_vars):
    script = REPO / "benchmarks" / "gpu_throughput.sh"
    env = {**os.environ, "PYTHON": sys.executable, **env_vars}
    return subprocess.run(["bash", str(script), str(tmp_path / "out"), *parts], env=env, capture_output=True,
                          text=True, timeout=900)  # fmt: skip


@pytest.mark.parametrize("part", ["warp-drive", "fit-1", "fit-x"])
def test_the_gpu_suite_rejects_an_unknown_part_before_any_work(tmp_path, part):
    done = _suite(tmp_path, "eager", part)
    assert done.returncode == 2 and f"unknown part '{part}'" in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message given where CUDA is missing")
def test_the_gpu_suite_says_it_needs_cuda(tmp_path):
    done = _suite(tmp_path)
    assert done.returncode == 2 and "CUDA is not available" in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow  # five Lightning runs in subprocesses: 2-7 min on the 2-core machine
def test_the_gpu_suite_rehearsed_on_the_cpu_resumes_and_compares(bench, tmp_path):
    """DEVICE=cpu runs the suite's training parts: each leaves its table and loss curve, a failed part leaves
    no table (so it runs again), a second run skips what is done, and the comparisons are against eager; the
    fit part reads `aesplat fit`'s own logs."""
    rehearse = {
        "DEVICE": "cpu",
        "CONFIG": SMOKE,
        "STEPS": "2",
        "WARMUP": "0",
        "FIT_STEPS": "4",
        "FIT_WINDOW": "2",
    }
    out = tmp_path / "out"
    failed = _suite(tmp_path, "eager", **rehearse, SEED="zero")
    assert failed.returncode != 0 and not (out / "eager.md").exists()
    assert "--seed: invalid int value" in (out / "eager.log").read_text()

    done = _suite(tmp_path, **rehearse)
    assert done.returncode == 0, done.stderr
    for part in ("eager", "eager-again", "tuned", "bf16-heads"):
        assert "| seconds per step (median) |" in (out / f"{part}.md").read_text()
        assert sorted(bench.read_losses(out / f"{part}.csv")) == [0, 1]
    assert "| max relative difference, per step | 0 |" in (out / "eager-again.md").read_text()
    assert f"against {out / 'eager.csv'}" in (out / "bf16-heads.md").read_text()
    assert "no CUDA" in (out / "versions.txt").read_text()
    fit = (out / "fit.md").read_text()
    assert (
        "$ aesplat fit -c" in fit
        and "| windows after the first | 1 |" in fit
        and "| skipped steps | 0 |" in fit
    )
    assert (out / "fit" / "run" / "metrics.csv").is_file()
    fit3 = json.loads((out / "fit-3.json").read_text())  # three context views, the pooled head, the same shards
    assert fit3["context_views"] == 3 and "--model.net.view_aggregation pool" in fit3["command"]
    assert f"--data.root {out / 'shards'}" in fit3["command"] and fit3["figures"]["skipped steps"] == 0

    again = _suite(tmp_path, **rehearse)
    assert again.returncode == 0 and again.stdout.count("done before") == 6

    needs_cuda = _suite(tmp_path, "render", **rehearse)
    assert needs_cuda.returncode == 2 and "need CUDA" in needs_cuda.stderr


def test_the_fit_part_reads_its_figures_from_the_run_logs(tmp_path):
    fit = load_benchmark("fit_throughput")
    rows = [  # as the CSV logger writes them: the throughput windows and the module's scalars on their own rows
        {"step": 9, "train/sec_per_step": 5.0, "train/samples_per_sec": 2.0, "train/peak_memory_gib": 1.0},
        {"step": 9, "train/loss": 0.1, "train/skipped_steps": 0},
        {"step": 19, "train/sec_per_step": 0.4, "train/samples_per_sec": 25.0, "train/peak_memory_gib": 3.0},
        {"step": 29, "train/sec_per_step": 0.6, "train/samples_per_sec": 16.0, "train/peak_memory_gib": 2.5},
        {"step": 39, "train/sec_per_step": 0.5, "train/samples_per_sec": 20.0, "train/peak_memory_gib": 2.5},
        {"step": 39, "train/loss": 0.1, "train/skipped_steps": 2},
        # stopped by a signal at step 40: the last window logged again, the same values, is no fourth window
        {"step": 40, "train/sec_per_step": 0.5, "train/samples_per_sec": 20.0, "train/peak_memory_gib": 2.5},
    ]
    path = tmp_path / "metrics.csv"
    keys = ["step", "train/sec_per_step", "train/samples_per_sec", "train/peak_memory_gib", "train/loss",
            "train/skipped_steps"]  # fmt: skip
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    out = fit.summarize(path)
    assert out["windows after the first"] == 3 and out["first window, s / step (compilation, warm-up)"] == 5.0
    assert out["seconds per step (median)"] == 0.5 and out["samples / s (median)"] == 20.0
    assert out["peak memory (GiB)"] == 3.0 and out["skipped steps"] == 2
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows[:2])
    with pytest.raises(SystemExit, match="1 throughput window"):
        fit.summarize(path)
