"""Learning curves: benchmarks/learning_curves.py with the LearningCurve callback, on the smoke shards."""

import math
from pathlib import Path

import torch

from ..script_loader import load_benchmark

curves = load_benchmark("curves")
CURVE_COLUMNS, read_curve, write_curve = curves.CURVE_COLUMNS, curves.read_curve, curves.write_curve

ROOT = Path(__file__).resolve().parents[2]


def _driver():
    return load_benchmark("learning_curves")


def _run(driver, shards: Path, out: Path, steps: int, runs: list[str]) -> None:
    argv = ["--config", str(ROOT / "conf" / "smoke.yaml"), "--data", str(shards.parent), "--size", "28",
            "--steps", str(steps), "--every", "1", "--out", str(out), "--runs", *runs]  # fmt: skip
    assert driver.main(argv) == 0


def test_curves_of_pose_free_and_posed_runs_then_resume_without_reevaluating(smoke_shards, tmp_path):
    driver = _driver()
    out = tmp_path / "curves"
    _run(driver, smoke_shards, out, 2, ["pose-free", "posed"])
    free, posed = read_curve(out / "pose-free" / "curve.csv"), read_curve(out / "posed" / "curve.csv")
    for rows in (free, posed):
        assert [r["step"] for r in rows] == [0, 1, 2]
        assert rows[0]["train_seconds"] == 0 and rows[0]["train_seconds"] < rows[1]["train_seconds"]
        assert rows[1]["train_seconds"] < rows[2]["train_seconds"]
        assert all(math.isfinite(r["psnr"]) and 0 < r["ssim"] <= 1 and r["num_scenes"] == 2 for r in rows)
    assert all(math.isfinite(r["rot_err_deg"]) and math.isfinite(r["trans_err_deg"]) for r in free)
    assert all(math.isnan(r["rot_err_deg"]) for r in posed)  # given cameras: no pose error to measure
    # Same test scenes: the copy yardsticks agree across runs and points; the untrained models differ only
    # in where their cameras come from.
    assert {(r["copy_mean_psnr"], r["copy_best_psnr"]) for r in free + posed} == {
        (free[0]["copy_mean_psnr"], free[0]["copy_best_psnr"])
    }
    assert (out / "curves.png").stat().st_size > 0
    table = (out / "CURVES.md").read_text()
    assert "| pose-free | 2 |" in table and "| posed | 2 |" in table and "n/a → n/a" in table

    # An interrupted curve: a row written after the last checkpoint (step 2) is stale, the longer run resumes
    # from step 2 and keeps the finished points as they were; the finished posed run is not trained again.
    stale = {**free[-1], "step": 3, "psnr": 99.0}
    write_curve(out / "pose-free" / "curve.csv", [*free, stale])
    posed_csv = (out / "posed" / "curve.csv").read_text()
    _run(driver, smoke_shards, out, 4, ["pose-free"])
    resumed = read_curve(out / "pose-free" / "curve.csv")
    assert [r["step"] for r in resumed] == [0, 1, 2, 3, 4]
    assert resumed[:3] == free, "finished points are not evaluated again"
    assert resumed[3]["psnr"] != 99.0 and resumed[3]["train_seconds"] > free[2]["train_seconds"]
    assert (out / "posed" / "curve.csv").read_text() == posed_csv
    assert list(read_curve(out / "posed" / "curve.csv")[0]) == list(CURVE_COLUMNS)


def test_warm_start_run_pretrains_once_on_other_scenes_then_starts_from_that_checkpoint(smoke_shards, tmp_path):
    from omegaconf import OmegaConf

    driver = _driver()
    warm_overlay = tmp_path / "smoke_warmstart.yaml"  # on the smoke config, as conf/warmstart.yaml on the demo
    net, loss = {"options": {"camera_correlation": True}}, {"pose_weight": 1.0, "pose_rotation_weight": 10.0}
    OmegaConf.save(OmegaConf.create({"model": {"cameras": "dataset", "net": net, "loss": loss}}), warm_overlay)
    out = tmp_path / "curves"
    scenes = "--seed 1 --scenes 2 --test-scenes 1 --frames 12 --height 48 --width 64"
    argv = ["--config", str(ROOT / "conf" / "smoke.yaml"), "--data", str(smoke_shards.parent), "--size", "28",
            "--steps", "1", "--every", "1", "--out", str(out), "--runs", "pose-free", "warm-start",
            "--warm-start-config", str(ROOT / "conf" / "smoke.yaml"), str(warm_overlay),
            "--warm-start-steps", "2",
            "--warm-start-scene-args", scenes]  # fmt: skip
    assert driver.main(argv) == 0
    last = out / "warm-start-pretraining" / "checkpoints" / "last.ckpt"
    assert driver.checkpoint_step(last) == 2
    free, warm = read_curve(out / "pose-free" / "curve.csv"), read_curve(out / "warm-start" / "curve.csv")
    assert warm[0]["psnr"] != free[0]["psnr"]  # step 0 is the warm-started model, not the untrained one
    assert warm[0]["copy_mean_psnr"] == free[0]["copy_mean_psnr"]  # on the same test scenes
    hparams = torch.load(out / "warm-start" / "checkpoints" / "last.ckpt", weights_only=True)[
        "hyper_parameters"
    ]
    assert hparams["net"]["options"]["camera_correlation"] is True and hparams["optim"]["lr"] == 5e-5
    stamp = last.stat().st_mtime_ns
    assert driver.main(argv) == 0  # finished: neither the warm start nor the curves train again
    assert last.stat().st_mtime_ns == stamp


def test_data_seeds_train_each_run_once_per_seed_and_report_its_interval(smoke_shards, tmp_path):
    driver = _driver()
    out = tmp_path / "curves"
    argv = ["--config", str(ROOT / "conf" / "smoke.yaml"), "--data", str(smoke_shards.parent), "--size", "28",
            "--steps", "1", "--every", "1", "--out", str(out), "--runs", "pose-free",
            "--data-seeds", "0", "1"]  # fmt: skip
    assert driver.main(argv) == 0
    curves = [read_curve(out / f"pose-free@data-seed-{seed}" / "curve.csv") for seed in (0, 1)]
    assert not (out / "pose-free").exists()
    assert curves[0][0]["psnr"] == curves[1][0]["psnr"]  # the same model at step 0 ...
    assert curves[0][1]["psnr"] != curves[1][1]["psnr"]  # ... trained on other samples
    for seed in (0, 1):
        state = torch.load(out / f"pose-free@data-seed-{seed}" / "checkpoints" / "last.ckpt", weights_only=True)
        assert state["DataModule"]["seed"] == seed
    table = (out / "CURVES.md").read_text()
    mean, half, n = driver.t_interval([rows[-1]["psnr"] for rows in curves])
    assert n == 2 and half > 0
    assert "| pose-free, mean ± 95 % interval over 2 data seeds | 1 |" in table
    assert f"→ {mean:.2f} ± {half:.2f} |" in table


def test_context_baselines_average_like_aesplat_test():
    target = torch.full((1, 2, 3, 4, 4), 0.5)
    same = torch.full((1, 1, 3, 4, 4), 0.5)
    off = torch.full((1, 1, 3, 4, 4), 0.6)  # MSE 0.01 -> 20 dB
    scenes = [
        (torch.cat([off, off], 1), target),  # both views 20 dB, their mean too
        (torch.cat([same + 0.2, off], 1), target),  # views 0.7 (14 dB) and 0.6 (20 dB), mean 0.65 (16.48 dB)
    ]
    values = curves.context_copy_psnr(scenes)
    assert abs(values[curves.COPY_BEST] - 20.0) < 1e-4
    mean = (20.0 + 10 * math.log10(1 / 0.15**2)) / 2
    assert abs(values[curves.COPY_MEAN] - mean) < 1e-4
