"""benchmarks/appearance_ablation.py: its statistics, and a tiny grid run end to end with resumption."""

import csv
import json
from pathlib import Path

import pytest

from tests.script_loader import load_benchmark


def _runner():
    return load_benchmark("appearance_ablation")


def test_paired_differences_pair_by_seed():
    runner = _runner()
    run = runner.Run
    results = {run("specular", "dataset", "full", 0): {"psnr": 20.0},
               run("specular", "dataset", "full", 1): {"psnr": 22.0},
               run("specular", "dataset", "baseline", 0): {"psnr": 19.0},
               run("specular", "dataset", "baseline", 1): {"psnr": 21.5},
               run("specular", "dataset", "baseline", 2): {"psnr": 30.0}}  # fmt: skip
    diffs = runner.paired_differences(results, "specular", "dataset", "baseline", [0, 1, 2], "psnr")
    assert diffs == [-1.0, -0.5]  # seed 2 has no `full` to pair with


# Every run of these grids: 2 steps at 28x28, one test scene, SH degree 1, no workers.
TINY = ["--steps", "2", "--size", "28", "--scenes", "2", "--test-scenes", "1", "--", "--data.num_workers", "0",
        "--data.train_batches_per_epoch", "2", "--data.batch_size", "1", "--data.shuffle_buffer", "4",
        "--model.net.sh_degree", "1", "--model.eval.num_sample_renders", "0",
        "--last_checkpoint.every_n_train_steps", "2"]  # fmt: skip


def _grid(tmp_path: Path, *options: str) -> tuple[list[str], list[dict], dict]:
    """Run a tiny grid; returns its arguments, runs.csv and table.csv (keyed by set, cameras and row)."""
    args = ["--work", str(tmp_path / "work"), "--out", str(tmp_path / "out"), *options, *TINY]
    _runner().main(args)
    with open(tmp_path / "out" / "runs.csv") as f:
        runs = list(csv.DictReader(f))
    with open(tmp_path / "out" / "table.csv") as f:
        table = {(r["set"], r["cameras"], r["row"]): r for r in csv.DictReader(f)}
    return args, runs, table


def _psnr(runs: list[dict], dataset: str, cameras: str, row: str) -> list[float]:
    return [float(r["psnr"]) for r in runs if (r["set"], r["cameras"], r["row"]) == (dataset, cameras, row)]


def test_two_run_grid_reports_and_resumes(tmp_path, monkeypatch):
    """The CI-sized grid: `full` and `i2dc_only`, posed, one seed, the specular set."""
    args, runs, table = _grid(tmp_path, "--rows", "full", "i2dc_only", "--sets", "specular", "--seeds", "1",
                              "--free-seeds", "0")  # fmt: skip
    assert [(r["set"], r["cameras"], r["row"], r["seed"]) for r in runs] == [
        ("specular", "dataset", "full", "0"), ("specular", "dataset", "i2dc_only", "0")]  # fmt: skip
    work = tmp_path / "work"
    for r in runs:  # each row's figures are its own run's, as `aesplat test` scored them scene by scene
        folder = work / "runs" / "specular_dataset" / r["row"] / "seed0" / "test-latest"
        with open(folder / "per_scene.csv") as f:
            scenes = list(csv.DictReader(f))
        for metric in ("psnr", "psnr_rest", "ssim"):
            mean = sum(float(s[metric]) for s in scenes) / len(scenes)
            assert float(r[metric]) == pytest.approx(mean, rel=1e-6), (r["row"], metric)
        assert float(r["psnr"]) != float(r["psnr_rest"]) and float(r["fit_seconds"]) > 0
    assert runs[0]["psnr"] != runs[1]["psnr"]  # two appearance heads, two results
    assert json.loads((work / "shards" / "specular" / "manifest.json").read_text())["splits"]["test"][
        "highlight_share"] > 0.01  # fmt: skip
    line = table[("specular", "dataset", "i2dc_only")]
    diff = _psnr(runs, "specular", "dataset", "i2dc_only")[0] - _psnr(runs, "specular", "dataset", "full")[0]
    assert float(line["psnr_vs_full"]) == pytest.approx(diff, abs=1e-9)
    assert line["n"] == "1" and line["psnr_ci"] == "" and line["psnr_vs_full_ci"] == ""  # one seed: no interval
    assert "## specular set, posed" in (tmp_path / "out" / "table.md").read_text()
    # What the view-dependent part learned: measured from each checkpoint, none for the row without it.
    energy = {r["row"]: r for r in runs}
    assert float(energy["full"]["sh_high"]) > 0 and float(energy["full"]["sh_high_ratio"]) > 0
    assert energy["i2dc_only"]["sh_high"] == ""
    assert "## What the view-dependent part learned" in (tmp_path / "out" / "table.md").read_text()
    assert (tmp_path / "out" / "ablation.png").stat().st_size > 0
    config = (work / "runs" / "specular_dataset" / "i2dc_only" / "seed0" / "config.yaml").read_text()
    assert "appearance: i2dc_only" in config and "cameras: dataset" in config

    # Resumption: finished runs are not retrained; a run without its result is, alone.
    runner = _runner()
    calls = []
    monkeypatch.setattr(runner, "train_and_test", lambda run, *a: calls.append(run))
    runner.main(args)
    assert calls == []
    (work / "runs" / "specular_dataset" / "full" / "seed0" / "test-latest" / "summary.json").unlink()
    with pytest.raises(RuntimeError, match="without"):  # the stub writes no result, which is an error
        runner.main(args)
    assert calls == [runner.Run("specular", "dataset", "full", 0)]
    # Other settings never reuse these results.
    with pytest.raises(SystemExit, match="other settings"):
        runner.main([*args[:-1], "4"])


@pytest.mark.slow
def test_full_tiny_grid_both_sets_and_pose_free(tmp_path):
    """Both sets posed with two seeds, and pose-free on the specular set: 10 runs."""
    _, runs, table = _grid(tmp_path, "--rows", "full", "i2dc_only", "--seeds", "2", "--free-seeds", "1")
    assert len(runs) == 10
    assert {(r["set"], r["cameras"]) for r in runs} == {("specular", "dataset"), ("diffuse", "dataset"),
                                                        ("specular", "predicted")}  # fmt: skip
    for r in runs:  # the diffuse control has no highlight pixel: no highlight PSNR, the rest is the whole image
        if r["set"] == "diffuse":
            assert r["psnr_highlight"] == "" and float(r["psnr_rest"]) == pytest.approx(float(r["psnr"]), 1e-4)
    line = table[("specular", "dataset", "i2dc_only")]
    full, mine = _psnr(runs, "specular", "dataset", "full"), _psnr(runs, "specular", "dataset", "i2dc_only")
    assert float(line["psnr"]) == pytest.approx(sum(mine) / 2, abs=1e-9)
    assert float(line["psnr_vs_full"]) == pytest.approx((mine[0] - full[0] + mine[1] - full[1]) / 2, abs=1e-9)
    assert line["n"] == "2" and line["psnr_vs_full_ci"] != ""
    assert table[("specular", "predicted", "full")]["psnr_ci"] == ""  # one seed: no interval
    text = (tmp_path / "out" / "table.md").read_text()
    assert "## diffuse set, posed" in text and "pose-free" in text


def test_primary_family_holm_adjusts_the_named_comparisons_only(tmp_path):
    runner = _runner()
    paired_t_p = runner.paired_t_p
    run = runner.Run
    full = {0: 20.0, 1: 21.0, 2: 22.0}
    worse = {0: 18.0, 1: 18.5, 2: 19.6}  # highlight PSNR: clearly below `full` in every seed
    same = {0: 20.1, 1: 20.8, 2: 22.1}
    results = {}
    for seed in range(3):
        results[run("specular", "dataset", "full", seed)] = {"psnr": 1.0, "psnr_highlight": full[seed]}
        results[run("specular", "dataset", "baseline", seed)] = {"psnr": 9.0, "psnr_highlight": worse[seed]}
        results[run("diffuse", "dataset", "full", seed)] = {"psnr": full[seed]}
        results[run("diffuse", "dataset", "baseline", seed)] = {"psnr": same[seed]}
    runs = list(results)
    family = runner.primary_family(results, runs, ["full", "baseline"])
    assert [(x["set"], x["metric"], x["row"]) for x in family] == [
        ("specular", "psnr_highlight", "baseline"),
        ("diffuse", "psnr", "baseline"),
    ]  # overall PSNR of the specular set (9 vs 1 dB) is not in the family
    p_hl = paired_t_p([worse[s] - full[s] for s in range(3)])[0]
    p_diffuse = paired_t_p([same[s] - full[s] for s in range(3)])[0]
    assert family[0]["p"] == p_hl and family[1]["p"] == p_diffuse and p_hl < p_diffuse
    assert family[0]["p_holm"] == 2 * p_hl and family[1]["p_holm"] == max(2 * p_hl, p_diffuse)
    assert family[0]["n"] == 3 and family[0]["diff"] < 0

    # The report from a runs.csv alone: the same family in primary.csv and table.md.
    out = tmp_path / "out"
    runner.write_report(out, runs, results, ["full", "baseline"], runner.Settings("c", 28, 2, 2, 1, 0, ()))
    rebuilt = tmp_path / "rebuilt"
    runner.main(["--from-runs", str(out / "runs.csv"), "--out", str(rebuilt), "--rows", "full", "baseline",
                 "--seeds", "3", "--free-seeds", "0"])  # fmt: skip
    with open(rebuilt / "primary.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["p_holm"]) for r in rows] == pytest.approx([x["p_holm"] for x in family])
    assert "## Primary comparisons (Holm-adjusted)" in (rebuilt / "table.md").read_text()


def test_the_headline_tables_mark_the_differences_whose_interval_excludes_zero():
    runner = _runner()
    line = {"set": "specular", "cameras": "dataset", "psnr": 20.0, "psnr_ci": 0.3, "psnr_highlight": 21.0,
            "psnr_highlight_ci": 1.0}  # fmt: skip
    lines = [{**line, "row": "full"},
             {**line, "row": "baseline", "psnr_vs_full": -3.9, "psnr_vs_full_ci": 0.2,
              "psnr_highlight_vs_full": 0.5, "psnr_highlight_vs_full_ci": 1.0}]  # fmt: skip
    text = runner.headline_markdown(lines)
    assert "| `full` | 20.00 ± 0.30 |  | 21.00 ± 1.00 |  |" in text
    assert "| `baseline` | 20.00 ± 0.30 | **-3.90 ± 0.20** | 21.00 ± 1.00 | +0.50 ± 1.00 |" in text
