"""Image metrics, relative pose errors and the evaluation writers."""

import csv
import json
import math
import os

import pytest
import torch

from aesplat.geometry import make_pose, quat_to_matrix
from aesplat.images import save_image
from aesplat.train.evaluation import summarize, visual_grid, write_results
from aesplat.train.metrics import (
    highlight_psnr,
    masked_psnr,
    overlap_bucket,
    psnr,
    relative_pose_errors,
    ssim,
)


def test_psnr_is_per_image():
    target = torch.zeros(2, 3, 8, 8)
    pred = target.clone()
    pred[0] += 0.1  # MSE 0.01 -> 20 dB
    pred[1] += 0.01  # MSE 1e-4 -> 40 dB
    assert psnr(pred, target).tolist() == pytest.approx([20.0, 40.0], rel=1e-4)


def test_masked_psnr_by_hand():
    target = torch.zeros(3, 3, 4, 4)
    pred = target.clone()
    mask = torch.zeros(3, 1, 4, 4, dtype=torch.bool)
    mask[0, :, 0, :2] = True  # image 0: two highlight pixels, off by 0.1 and 0.3 in every channel
    pred[0, :, 0, 0], pred[0, :, 0, 1] = 0.1, 0.3
    pred[0, :, 3, 3] = 0.5  # outside the mask: ignored by the highlight PSNR
    mask[1] = True  # image 1: every pixel; off by 0.1 -> 20 dB
    pred[1] += 0.1
    pred[2, 0] = 1.5  # image 2: empty mask; the prediction is clamped to 1 like `psnr`
    got = masked_psnr(pred, target, mask)
    expect_0 = -10 * math.log10((0.1**2 + 0.3**2) / 2)  # mean over the 2 pixels x 3 channels
    assert got[0].item() == pytest.approx(expect_0, rel=1e-5)
    assert got[1].item() == pytest.approx(20.0, rel=1e-5)
    assert math.isnan(got[2].item())  # no such pixels: NaN, not a number made up
    assert masked_psnr(pred[1:2], target[1:2], mask[1:2]).item() == pytest.approx(
        psnr(pred[1:2], target[1:2]).item()
    )

    split = highlight_psnr(pred, target, mask)
    assert split["psnr_highlight"][0].item() == pytest.approx(expect_0, rel=1e-5)
    rest_0 = -10 * math.log10(0.5**2 / 14)  # the 14 other pixels: one off by 0.5
    assert split["psnr_rest"][0].item() == pytest.approx(rest_0, rel=1e-5)
    assert math.isnan(split["psnr_rest"][1].item())  # everything is highlight: no rest
    assert split["psnr_rest"][2].item() == pytest.approx(
        -10 * math.log10(1 / 3), rel=1e-5
    )  # 1/3 of values off by 1
    assert split["highlight_fraction"].tolist() == pytest.approx([2 / 16, 1.0, 0.0])


def test_empty_highlight_metrics_are_blank_in_the_csv_and_skipped_in_the_summary(tmp_path):
    rows = _rows()
    for i, row in enumerate(rows):
        row.update(
            psnr_highlight=float("nan") if i < 2 else 10.0 * i, psnr_rest=30.0, highlight_fraction=0.1 * i
        )
    summary = write_results(rows, tmp_path)
    assert summary["metrics"]["psnr_highlight"] == pytest.approx(30.0)  # mean of 20, 30, 40
    assert summary["counts"]["psnr_highlight"] == 3 and summary["counts"]["psnr_rest"] == 5
    with open(tmp_path / "per_scene.csv") as f:
        table = list(csv.DictReader(f))
    assert [r["psnr_highlight"] for r in table] == ["", "", "20.0", "30.0", "40.0"]
    assert summarize(_rows())["metrics"]["psnr_highlight"] is None  # data without masks: null


def test_evaluation_stopped_while_writing_leaves_no_summary(tmp_path, monkeypatch):
    """A crash while summary.json is being written leaves none (never a truncated one that reads as a
    finished evaluation) and a whole per_scene.csv beside it."""
    real_fsync, calls = os.fsync, []

    def crash_on_second_file(fd):
        calls.append(fd)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", crash_on_second_file)
    with pytest.raises(KeyboardInterrupt):
        write_results(_rows(), tmp_path)
    assert not (tmp_path / "summary.json").exists()
    with open(tmp_path / "per_scene.csv") as f:
        assert len(list(csv.DictReader(f))) == len(_rows())
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == ["per_scene.csv"]


def test_ssim_identity_and_noise():
    image = torch.rand(2, 3, 32, 32)
    assert ssim(image, image).tolist() == pytest.approx([1.0, 1.0], abs=1e-5)
    noisy = (image + 0.3 * torch.randn_like(image)).clamp(0, 1)
    assert (ssim(noisy, image) < 0.9).all()


def _random_poses(b, v, generator):
    q = torch.randn(b, v, 4, generator=generator)
    t = torch.randn(b, v, 3, generator=generator)
    return make_pose(quat_to_matrix(q), t)


def test_pose_errors_ignore_world_frame_and_scale():
    g = torch.Generator().manual_seed(0)
    gt = _random_poses(2, 3, g)
    world = _random_poses(2, 1, g)
    # The prediction lives in another world frame and at another scale: errors must still be zero.
    pred = world @ gt
    pred[..., :3, 3] *= 3.0
    rot, trans = relative_pose_errors(pred, gt)
    assert rot.shape == trans.shape == (2, 2)
    assert rot.abs().max() < 1e-2 and trans.abs().max() < 1e-2


def test_pose_errors_known_angles():
    eye = torch.eye(4)
    gt = torch.stack([eye, make_pose(torch.eye(3), torch.tensor([1.0, 0.0, 0.0]))])[None]
    angle = math.radians(30.0)
    rot_z = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]]
    )
    pred = torch.stack([eye, make_pose(rot_z, torch.tensor([0.0, 2.0, 0.0]))])[None]
    rot, trans = relative_pose_errors(pred, gt)
    assert rot.item() == pytest.approx(30.0, abs=1e-3)
    assert trans.item() == pytest.approx(90.0, abs=1e-3)


def test_overlap_buckets():
    assert overlap_bucket(0.1) == "small"
    assert overlap_bucket(0.4) == "medium"
    assert overlap_bucket(0.9) == "large"
    assert overlap_bucket(float("nan")) == "unknown"
    assert overlap_bucket(None) == "unknown"


def _rows():
    rows = []
    for i, (overlap, value) in enumerate([(0.1, 10.0), (0.2, 12.0), (0.4, 20.0), (0.8, 30.0), (None, 40.0)]):
        rows.append({"scene": f"s{i}", "dataset": "synthetic", "overlap": overlap,
                     "bucket": overlap_bucket(overlap), "gap": 5, "psnr": value, "ssim": 0.5,
                     "lpips": None, "rot_err_deg": 1.0, "trans_err_deg": 2.0})  # fmt: skip
    return rows


def test_summary_means_and_buckets():
    summary = summarize(_rows(), lpips_unavailable="no weights")
    assert summary["num_scenes"] == 5
    assert summary["metrics"]["psnr"] == pytest.approx(22.4)
    assert summary["metrics"]["lpips"] is None
    assert summary["unavailable"] == {"lpips": "no weights"}
    assert summary["buckets"]["small"]["psnr"] == pytest.approx(11.0)
    assert summary["buckets"]["small"]["num_scenes"] == 2
    assert summary["buckets"]["medium"]["psnr"] == pytest.approx(20.0)
    assert summary["buckets"]["large"]["psnr"] == pytest.approx(30.0)
    assert summary["buckets"]["unknown"]["num_scenes"] == 1


def test_write_results_csv_and_json(tmp_path):
    summary = write_results(list(reversed(_rows())), tmp_path / "out")
    with open(tmp_path / "out" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["scene"] for r in rows] == ["s0", "s1", "s2", "s3", "s4"]
    assert rows[0]["bucket"] == "small" and float(rows[0]["psnr"]) == 10.0 and rows[0]["lpips"] == ""
    assert json.loads((tmp_path / "out" / "summary.json").read_text()) == summary


def test_visual_grid_and_png(tmp_path):
    ctx, tgt = torch.rand(2, 2, 3, 8, 10), torch.rand(2, 1, 3, 8, 10)
    grid = visual_grid(ctx, tgt, tgt, torch.rand(2, 1, 1, 8, 10))
    assert grid.shape == (3, 16, 50)
    assert torch.equal(grid[:, 8:16, 0:10], ctx[1, 0])
    save_image(grid, tmp_path / "g.png")
    assert (tmp_path / "g.png").stat().st_size > 0
