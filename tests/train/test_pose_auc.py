"""The pose AUC of the pose-free literature: the context views' errors (last view vs view 0, and the mean over
views 1..V-1), the AUC at 5/10/20°, the summary's groups, the CSV columns and the logged scalars."""

import csv
import json
import math
from types import SimpleNamespace

import pytest
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from aesplat.data.validate import EvaluationEntry, read_evaluation_index
from aesplat.geometry import intrinsics_from_fov, make_pose, quat_to_matrix
from aesplat.train import AESplatModule
from aesplat.train.evaluation import POSE_AUC_METRICS, pose_auc_scalars, summarize, write_results
from aesplat.train.metrics import context_pose_errors, overlap_bucket, pose_auc
from aesplat.types import BatchedExample, BatchedViews
from tests.train.helpers import make_trainer

# ----------------------------------------------------------------------------------------------- pose_auc


def test_pose_auc_integrates_the_recall_curve_up_to_each_threshold():
    # Sorted errors 1, 3, 7, 15, 30 of 5 scenes: the curve runs through (0, 0), (1, .2), (3, .4), (7, .6),
    # (15, .8), (30, 1), linear between the points, and stays at the last recall below the threshold up to it.
    # At 5:  (0+.2)/2*1 + (.2+.4)/2*2 + (.4+.4)/2*2    = .1 + .6 + .8         = 1.5  / 5  = .3
    # At 10: .1 + .6 + (.4+.6)/2*4 + (.6+.6)/2*3     = .1 + .6 + 2.0 + 1.8  = 4.5  / 10 = .45
    # At 20: .1 + .6 + 2.0 + (.6+.8)/2*8 + (.8+.8)/2*5 = 2.7 + 5.6 + 4.0    = 12.3 / 20 = .615
    # (A step curve would give 1.2 / 5 at 5; interpolating to the threshold 1.6 / 5.)
    assert pose_auc([15.0, 1.0, 30.0, 7.0, 3.0]) == pytest.approx([0.3, 0.45, 0.615])
    assert pose_auc([15.0, 1.0, 30.0, 7.0, 3.0], thresholds=(10,)) == pytest.approx([0.45])


def test_an_error_equal_to_the_threshold_does_not_count():
    assert pose_auc([5.0], thresholds=(5,)) == [0.0]
    # (0, 0) to (4, 1), then flat to 5: (2 + 1) / 5
    assert pose_auc([4.0], thresholds=(5,)) == pytest.approx([0.6])
    assert pose_auc([0.0, 0.0]) == pytest.approx([1.0, 1.0, 1.0])
    # Equal errors: the curve climbs from (0, 0) to (3, .5), then straight up to (3, 1): (.75 + 2) / 5 at 5
    assert pose_auc([3.0, 3.0]) == pytest.approx([0.55, 0.775, 0.8875])


def test_pose_auc_needs_finite_errors():
    with pytest.raises(ValueError, match="at least one error"):
        pose_auc([])
    with pytest.raises(ValueError, match="all finite"):
        pose_auc([1.0, math.nan])


# ----------------------------------------------------------------------------------------------- errors


def _rot_y(degrees: float) -> Tensor:
    a = math.radians(degrees)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def _poses(turns: list[float], directions: list[float], scale: float = 1.0) -> Tensor:
    """Cameras [V, 4, 4] in view 0's frame: view 0 the identity, view i turned by ``turns[i-1]`` degrees about y
    and moved by ``scale`` in the direction ``directions[i-1]`` degrees from x in the x-y plane."""
    poses = [torch.eye(4)]
    for turn, direction in zip(turns, directions):
        d = math.radians(direction)
        poses.append(make_pose(_rot_y(turn), scale * torch.tensor([math.cos(d), math.sin(d), 0.0])))
    return torch.stack(poses)


def _world(seed: int) -> Tensor:
    """A world frame [4, 4]: the errors compare poses relative to view 0, whatever the frame."""
    gen = torch.Generator().manual_seed(seed)
    quat = torch.randn(4, generator=gen)
    return make_pose(quat_to_matrix(quat / quat.norm()), torch.randn(3, generator=gen))


def _errors(pred: Tensor, gt: Tensor) -> dict[str, list[float]]:
    """context_pose_errors of one scene or several ([B, V, 4, 4] or [V, 4, 4]), each in a different world."""
    pred, gt = (p if p.dim() == 4 else p[None] for p in (pred, gt))
    errors = context_pose_errors(_world(1) @ pred, _world(2) @ gt)
    return {k: v.tolist() for k, v in errors.items()}


def test_the_translation_angle_folds_to_min_of_e_and_180_minus_e():
    gt = _poses([0.0], [0.0])
    for off, folded in [(30.0, 30.0), (150.0, 30.0), (100.0, 80.0), (180.0, 0.0), (90.0, 90.0)]:
        errors = _errors(_poses([0.0], [off], scale=3.0), gt)  # the scale is free
        assert errors["trans_err_last_deg"] == pytest.approx([folded], abs=1e-3), off
        assert errors["rot_err_last_deg"] == pytest.approx([0.0], abs=1e-3)


def test_a_camera_that_did_not_move_has_no_direction_but_nan_stays_nan():
    gt = _poses([0.0], [0.0])
    assert _errors(_poses([0.0], [0.0], scale=0.0), gt)["trans_err_last_deg"] == [90.0]
    broken = _poses([0.0], [0.0])
    broken[1, 0, 3] = math.nan
    errors = context_pose_errors(broken[None], gt[None])
    assert math.isnan(errors["trans_err_last_deg"].item()) and math.isnan(errors["pose_err_last_deg"].item())


def test_the_pose_error_is_the_larger_of_rotation_and_translation():
    gt = torch.stack([_poses([20.0], [10.0]), _poses([20.0], [10.0])])
    pred = torch.stack([_poses([32.0], [13.0]), _poses([22.0], [50.0])])  # 12° and 3° off; 2° and 40° off
    errors = _errors(pred, gt)
    assert errors["rot_err_last_deg"] == pytest.approx([12.0, 2.0], abs=1e-3)
    assert errors["trans_err_last_deg"] == pytest.approx([3.0, 40.0], abs=1e-3)
    assert errors["pose_err_last_deg"] == pytest.approx([12.0, 40.0], abs=1e-3)


def test_last_view_against_the_mean_over_the_context_views():
    """Three context views: view 1 is 30° turned off with the right direction, view 2 turned right with its
    direction 20° off. The last view alone (NAS3R's) sees only view 2; the mean over views 1 and 2
    (SPFSplatV2's) sees both, and its pose error is the larger of the two means (15, not the mean of the
    per-view maxima, 25)."""
    gt = _poses([10.0, -5.0], [0.0, 60.0])
    pred = _poses([40.0, -5.0], [0.0, 80.0])
    errors = _errors(pred, gt)
    assert errors["rot_err_last_deg"] == pytest.approx([0.0], abs=1e-3)
    assert errors["trans_err_last_deg"] == pytest.approx([20.0], abs=1e-3)
    assert errors["pose_err_last_deg"] == pytest.approx([20.0], abs=1e-3)
    assert errors["rot_err_ctx_deg"] == pytest.approx([15.0], abs=1e-3)
    assert errors["trans_err_ctx_deg"] == pytest.approx([10.0], abs=1e-3)
    assert errors["pose_err_ctx_deg"] == pytest.approx([15.0], abs=1e-3)


def test_two_views_give_both_variants_the_same_errors():
    errors = _errors(_poses([7.0], [25.0]), _poses([0.0], [0.0]))
    for kind in ("rot", "trans", "pose"):
        assert errors[f"{kind}_err_ctx_deg"] == errors[f"{kind}_err_last_deg"]
    assert errors["pose_err_last_deg"] == pytest.approx([25.0], abs=1e-3)


# ----------------------------------------------------------------------------------------------- summary

# scene, overlap, context views, error e: rot = e, trans = e / 10, pose = e (last); the ctx columns are 2 e
SCENES = [("s0", 0.1, 2, 1.0), ("s1", 0.2, 2, 3.0), ("s2", 0.4, 3, 7.0), ("s3", 0.8, 3, 15.0),
          ("s4", 0.9, 3, 30.0), ("s5", 0.45, 4, math.nan)]  # fmt: skip


def _pose_rows() -> list[dict]:
    rows = []
    for scene, overlap, views, e in SCENES:
        rows.append({"scene": scene, "overlap": overlap, "bucket": overlap_bucket(overlap),
                     "context_views": views, "rot_err_last_deg": e, "trans_err_last_deg": e / 10,
                     "pose_err_last_deg": e, "rot_err_ctx_deg": 2 * e, "trans_err_ctx_deg": e / 5,
                     "pose_err_ctx_deg": 2 * e})  # fmt: skip
    rows.append({"scene": "s6", "overlap": None, "bucket": "unknown", "context_views": 2})  # no pose errors
    return rows


def test_the_summary_gives_aucs_and_medians_per_bucket_and_count_of_context_views():
    pose = summarize(_pose_rows())["pose"]
    assert pose["thresholds_deg"] == [5, 10, 20]
    last = pose["all"]["last"]
    assert last["auc"]["rot"] == pytest.approx({"5": 0.3, "10": 0.45, "20": 0.615})  # the hand-computed case
    assert last["auc"]["pose"] == pytest.approx({"5": 0.3, "10": 0.45, "20": 0.615})
    assert last["auc"]["trans"] == pytest.approx(
        dict(zip(["5", "10", "20"], pose_auc([0.1, 0.3, 0.7, 1.5, 3.0])))
    )
    assert last["auc"]["trans"]["5"] > last["auc"]["rot"]["5"]
    assert last["median"] == pytest.approx({"rot": 7.0, "trans": 0.7, "pose": 7.0})
    assert last["num_scenes"] == {"rot": 5, "trans": 5, "pose": 5}
    assert last["non_finite"] == {"rot": 1, "trans": 1, "pose": 1}  # s5, left out
    ctx = pose["all"]["ctx"]
    assert ctx["median"] == pytest.approx({"rot": 14.0, "trans": 1.4, "pose": 14.0})
    assert ctx["auc"]["rot"] == pytest.approx(dict(zip(["5", "10", "20"], pose_auc([2, 6, 14, 30, 60]))))

    buckets = pose["buckets"]
    assert set(buckets) == {"small", "medium", "large", "unknown"}
    # small: 1 and 3 -> (0, 0), (1, .5), (3, 1), flat to 5: (.25 + 1.5 + 2) / 5
    assert buckets["small"]["last"]["auc"]["rot"]["5"] == pytest.approx(0.75)
    assert buckets["small"]["last"]["median"]["rot"] == pytest.approx(2.0)
    # medium: 7 and a NaN -> (0, 0), (7, 1): nothing under 5, (3.5 + 3) / 10 at 10
    assert buckets["medium"]["last"]["auc"]["rot"] == pytest.approx({"5": 0.0, "10": 0.65, "20": 0.825})
    assert buckets["medium"]["last"]["non_finite"]["rot"] == 1
    # large: 15 and 30 -> (0, 0), (15, .5), flat to 20: (3.75 + 2.5) / 20
    assert buckets["large"]["last"]["auc"]["rot"] == pytest.approx({"5": 0.0, "10": 0.0, "20": 0.3125})
    assert buckets["unknown"] == {"last": None, "ctx": None}  # its one scene has no pose errors

    views = pose["context_views"]
    assert set(views) == {"2", "3", "4"}
    assert (
        views["2"]["last"]["median"]["rot"] == pytest.approx(2.0)
        and views["2"]["last"]["num_scenes"]["rot"] == 2
    )
    assert views["3"]["last"]["median"]["rot"] == pytest.approx(15.0)
    only_nan = views["4"]["last"]  # s5 alone: every error non-finite
    assert only_nan["auc"] == {"rot": None, "trans": None, "pose": None}
    assert only_nan["median"] == {"rot": None, "trans": None, "pose": None}
    assert only_nan["num_scenes"]["pose"] == 0 and only_nan["non_finite"]["pose"] == 1


def test_the_pose_summary_is_null_without_pose_errors():
    rows = [{k: v for k, v in row.items() if k not in POSE_AUC_METRICS} for row in _pose_rows()]
    assert summarize(rows)["pose"] is None  # the data set's cameras: no pose predicted
    last_only = [{k: v for k, v in row.items() if "_ctx_" not in k} for row in _pose_rows()]
    pose = summarize(last_only)["pose"]
    assert pose["all"]["ctx"] is None and pose["all"]["last"] is not None


def test_the_csv_has_the_pose_auc_columns(tmp_path):
    summary = write_results(_pose_rows(), tmp_path)
    with open(tmp_path / "per_scene.csv") as f:
        reader = csv.DictReader(f)
        table = {r["scene"]: r for r in reader}
    names = ["rot_err_last_deg", "trans_err_last_deg", "pose_err_last_deg", "rot_err_ctx_deg",
             "trans_err_ctx_deg", "pose_err_ctx_deg"]  # fmt: skip
    assert [c for c in reader.fieldnames if c in names] == names
    assert float(table["s2"]["rot_err_last_deg"]) == 7.0 and float(table["s2"]["trans_err_ctx_deg"]) == 1.4
    assert table["s5"]["pose_err_last_deg"] == "" and table["s6"]["rot_err_ctx_deg"] == ""  # NaN, absent
    assert json.loads((tmp_path / "summary.json").read_text())["pose"] == summary["pose"]
    assert summary["metrics"]["pose_err_last_deg"] == pytest.approx(11.2)  # the mean of 1, 3, 7, 15, 30


def test_the_logged_scalars_are_the_aucs_over_all_scenes():
    scalars = pose_auc_scalars(summarize(_pose_rows()))
    assert len(scalars) == 2 * 3 * 3
    assert scalars["test/auc5_rot_last"] == pytest.approx(0.3)
    assert scalars["test/auc20_pose_last"] == pytest.approx(0.615)
    assert (
        scalars["test/auc10_trans_ctx"] == summarize(_pose_rows())["pose"]["all"]["ctx"]["auc"]["trans"]["10"]
    )
    assert pose_auc_scalars({"pose": None}) == {}


# ----------------------------------------------------------------------------------------------- the module

SIZE = 16


def _batch(context_views: int, b: int = 2, name: str = "s") -> BatchedExample:
    def views(v: int, first: int) -> BatchedViews:
        centres = torch.zeros(b, v, 3)
        centres[..., 0] = 0.05 * torch.arange(first, first + v)
        return BatchedViews(
            images=torch.full((b, v, 3, SIZE, SIZE), 128, dtype=torch.uint8),
            extrinsics=make_pose(torch.eye(3).expand(b, v, 3, 3), centres),
            intrinsics=intrinsics_from_fov(torch.full((b, v), 1.0)),
            index=torch.arange(first, first + v).expand(b, v).clone(),
        )

    return BatchedExample(context=views(context_views, 0), target=views(1, context_views),
                          scene=[f"{name}{i}" for i in range(b)], overlap=torch.full((b,), 0.5),
                          gap=torch.full((b,), context_views - 1), dataset=["hand"] * b)  # fmt: skip


def _module(tmp_path, cameras: str = "predicted") -> AESplatModule:
    return AESplatModule(
        net={"size": "tiny", "sh_degree": 1, "view_aggregation": "pool", "far": 20.0},
        loss={"lpips_weight": 0.0},
        render={"backend": "torch"},
        eval={
            "output_dir": str(tmp_path / "test"),
            "num_sample_renders": 0,
            "metrics_lpips": False,
            "splat_metrics": False,
        },  # fmt: skip
        cameras=cameras,
    )


def _turned(batch: BatchedExample, degrees: list[float]) -> Tensor:
    """The batch's cameras [B, V, 4, 4] (context, then target), context view i+1 turned by ``degrees[i]``."""
    cameras = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1).clone()
    for i, turn in enumerate(degrees, start=1):
        cameras[:, i, :3, :3] = cameras[:, i, :3, :3] @ _rot_y(turn)
    return cameras


def _predicting(module: AESplatModule, monkeypatch, degrees: list[float]) -> None:
    """The module's forward replaced: cameras of ``_turned``, renders equal to the targets."""

    def forward(batch: BatchedExample, *args, **kwargs):
        color = (
            batch.target.images.float() / 255
            if batch.target.images.dtype == torch.uint8
            else batch.target.images
        )
        return SimpleNamespace(extrinsics=_turned(batch, degrees)), SimpleNamespace(color=color)

    monkeypatch.setattr(module, "forward", forward)


def test_the_module_scores_the_context_views_only_with_predicted_cameras(tmp_path, monkeypatch):
    module = _module(tmp_path)
    _predicting(module, monkeypatch, [30.0, 10.0])  # 3 context views
    metrics, _, _ = module._evaluate(_batch(3))
    assert metrics["rot_err_last_deg"].tolist() == pytest.approx([10.0, 10.0], abs=1e-3)
    assert metrics["rot_err_ctx_deg"].tolist() == pytest.approx([20.0, 20.0], abs=1e-3)
    assert metrics["pose_err_ctx_deg"].tolist() == pytest.approx([20.0, 20.0], abs=1e-3)

    posed = _module(tmp_path, cameras="dataset")
    _predicting(posed, monkeypatch, [30.0, 10.0])
    metrics, _, _ = posed._evaluate(_batch(3))
    assert not set(POSE_AUC_METRICS) & set(metrics)


def test_aesplat_test_writes_and_logs_the_pose_auc(tmp_path, monkeypatch):
    module = _module(tmp_path)
    _predicting(module, monkeypatch, [3.0])  # 2 context views, view 1 turned 3° off
    trainer = make_trainer(1, tmp_path, enable_checkpointing=False)
    trainer.test(module, dataloaders=DataLoader([_batch(2, 1, "a"), _batch(2, 1, "b")], batch_size=None))
    # Two scenes (one per batch), one error of 3° counted twice: (.75 + 2) / 5 at 5, (.75 + 7) / 10 at 10
    summary = json.loads((tmp_path / "test" / "summary.json").read_text())
    assert summary["pose"]["all"]["last"]["auc"]["pose"] == pytest.approx(
        {"5": 0.55, "10": 0.775, "20": 0.8875}
    )
    assert trainer.callback_metrics["test/auc5_pose_last"].item() == pytest.approx(0.55)
    assert trainer.callback_metrics["test/auc10_rot_ctx"].item() == pytest.approx(0.775)
    with open(tmp_path / "test" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["rot_err_last_deg"]) for r in rows] == pytest.approx([3.0, 3.0], abs=1e-3)


# ----------------------------------------------------------------------------------------------- the index


def test_nas3rs_evaluation_index_is_read_as_it_is(tmp_path):
    """An excerpt of NAS3R's RealEstate10K index: null entries, float overlaps, and targets that repeat a
    context frame (as 434 of its 5,601 entries and pixelSplat's index do)."""
    excerpt = (
        '{"4ec2510baca79e6b": {"context": [7, 88], "target": [15, 58, 83], "overlap": 0.4}, '
        '"b41487d0a4d2a27a": null, '
        '"4089ef1b1bdb1d36": {"context": [51, 114], "target": [51, 68, 98], "overlap": 0.63523}, '
        '"f91fbdea76207935": {"context": [5, 85], "target": [63, 69, 85], "overlap": 0.48249}}'
    )
    path = tmp_path / "evaluation_index_re10k.json"
    path.write_text(excerpt)
    index = read_evaluation_index(path)
    assert index == {
        "4ec2510baca79e6b": EvaluationEntry((7, 88), (15, 58, 83), 0.4),
        "b41487d0a4d2a27a": None,
        "4089ef1b1bdb1d36": EvaluationEntry((51, 114), (51, 68, 98), 0.63523),
        "f91fbdea76207935": EvaluationEntry((5, 85), (63, 69, 85), 0.48249),
    }
    assert overlap_bucket(index["4089ef1b1bdb1d36"].overlap) == "large"
