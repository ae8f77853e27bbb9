"""Training and evaluation when the number of context views changes from one batch to the next (hand-made
batches): a ``pool`` network takes them all, a ``concat`` one is refused in one line before any step."""

import csv
import json
from types import SimpleNamespace

import lightning as L
import pytest
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from aesplat.errors import UserError
from aesplat.geometry import intrinsics_from_fov, make_pose
from aesplat.train import AESplatModule
from aesplat.train.evaluation import summarize
from aesplat.train.module import context_view_counts
from aesplat.types import BatchedExample, BatchedViews
from tests.helpers import REPO
from tests.train.helpers import make_trainer

SIZE = 28


def _views(b: int, v: int, gen: torch.Generator, first_frame: int) -> BatchedViews:
    centres = torch.zeros(b, v, 3)
    centres[..., 0] = 0.05 * torch.arange(first_frame, first_frame + v)
    return BatchedViews(
        images=torch.randint(0, 256, (b, v, 3, SIZE, SIZE), generator=gen, dtype=torch.uint8),
        extrinsics=make_pose(torch.eye(3).expand(b, v, 3, 3), centres),
        intrinsics=intrinsics_from_fov(torch.full((b, v), 1.0)),
        index=torch.arange(first_frame, first_frame + v).expand(b, v).clone(),
    )


def _batch(context_views: int, seed: int, b: int = 2) -> BatchedExample:
    gen = torch.Generator().manual_seed(seed)
    return BatchedExample(
        context=_views(b, context_views, gen, 0),
        target=_views(b, 1, gen, context_views),
        scene=[f"s{seed}_{i}" for i in range(b)],
        overlap=torch.full((b,), 0.5),
        gap=torch.full((b,), context_views - 1),
        dataset=["hand"] * b,
    )


class HandMadeData(L.LightningDataModule):
    """Fixed batches, their context counts declared as a data module declares them (``num_context_views``)."""

    def __init__(self, counts: list[int], declared) -> None:
        super().__init__()
        self.batches = [_batch(c, seed) for seed, c in enumerate(counts)]
        self.num_context_views = declared

    def train_dataloader(self):
        return DataLoader(self.batches, batch_size=None)

    def test_dataloader(self):
        return DataLoader(self.batches, batch_size=None)


def _module(aggregation: str, tmp_path) -> AESplatModule:
    return AESplatModule(
        net={"size": "tiny", "sh_degree": 1, "view_aggregation": aggregation, "far": 20.0},
        loss={"lpips_weight": 0.0},
        optim={"warmup_steps": 1},
        render={"backend": "torch"},
        eval={"output_dir": str(tmp_path / "test"), "num_sample_renders": 1, "metrics_lpips": False},
    )


def test_a_pool_module_trains_and_tests_on_batches_of_different_counts(tmp_path):
    L.seed_everything(0)
    counts = [2, 4, 3, 2, 5]
    module, data = _module("pool", tmp_path), HandMadeData(counts, declared=[2, 5])
    before = {n: p.detach().clone() for n, p in module.model.named_parameter_groups()["appearance"]}
    trainer = make_trainer(len(counts), tmp_path, enable_checkpointing=False, log_every_n_steps=1)
    trainer.fit(module, datamodule=data)
    assert trainer.global_step == len(counts) and module.skipped_steps == 0
    assert trainer.callback_metrics["train/context_views"] == counts[-1]
    moved = [n for n, p in module.model.named_parameter_groups()["appearance"] if not torch.equal(p, before[n])]
    assert len(moved) == len(before)  # every appearance parameter trained, whatever the count

    trainer.test(module, datamodule=data)
    with open(tmp_path / "test" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted(int(r["context_views"]) for r in rows) == sorted(c for c in counts for _ in range(2))
    summary = json.loads((tmp_path / "test" / "summary.json").read_text())
    assert set(summary["context_views"]) == {"2", "3", "4", "5"}
    assert summary["context_views"]["2"]["num_scenes"] == 4 and summary["context_views"]["5"]["num_scenes"] == 2
    for per_count in summary["context_views"].values():
        assert per_count["psnr"] is not None and per_count["rot_err_deg"] is not None


def test_a_concat_module_refuses_a_data_count_it_cannot_take_before_any_step(tmp_path):
    module, data = _module("concat", tmp_path), HandMadeData([2, 3], declared=[2, 3])
    before = [p.detach().clone() for p in module.model.parameters()]
    trainer = make_trainer(2, tmp_path, enable_checkpointing=False, log_every_n_steps=1)
    with pytest.raises(UserError, match="view_aggregation: pool") as err:
        trainer.fit(module, datamodule=data)
    assert "\n" not in str(err.value)
    assert trainer.global_step == 0
    assert all(torch.equal(a, b) for a, b in zip(before, module.model.parameters()))


@pytest.mark.parametrize(
    ("declared", "counts"), [(2, [2]), ([2, 4], [2, 3, 4]), ((3, 3), [3]), (None, []), ("2", [])]
)
def test_context_view_counts_reads_a_number_or_a_range(declared, counts):
    class Data:
        num_context_views = declared

    assert context_view_counts(Data()) == counts
    assert context_view_counts(None) == []


def test_summary_gives_every_metric_per_context_count():
    rows = [
        {"scene": "a", "bucket": "small", "context_views": 2, "psnr": 20.0, "rot_err_deg": 2.0},
        {"scene": "b", "bucket": "small", "context_views": 2, "psnr": 22.0, "rot_err_deg": 4.0},
        {"scene": "c", "bucket": "large", "context_views": 4, "psnr": 25.0, "rot_err_deg": 1.0},
        {"scene": "d", "bucket": "large", "psnr": 30.0},  # written before the count was recorded
    ]
    per_count = summarize(rows)["context_views"]
    assert per_count["2"]["num_scenes"] == 2 and per_count["2"]["psnr"] == 21.0
    assert per_count["2"]["rot_err_deg"] == 3.0
    assert per_count["4"]["num_scenes"] == 1 and per_count["4"]["psnr"] == 25.0
    assert set(per_count) == {"2", "4"}


def test_fit_with_a_range_then_test_and_bench_at_each_count_on_the_same_targets(tmp_path, monkeypatch):
    """The commands end to end: `aesplat fit` of a pool model with data.num_context_views [2, 4] (the logged
    count follows the seeded draw of every step and varies), then `aesplat test --data.num_context_views k`
    and `aesplat bench --context-views` for k = 2, 3, 4: the shards' k-view contexts, the same target frames."""
    from aesplat.bench.command import main as bench
    from aesplat.data import convert_dataset, generate_dataset
    from aesplat.data.sampler import ContextCount
    from aesplat.lightning_cli import run_lightning

    monkeypatch.chdir(REPO)
    monkeypatch.setattr("sys.argv", ["aesplat"])  # the commands' own arguments only
    generate_dataset(tmp_path / "src", scenes=2, test_scenes=2, frames=12, height=32, width=40, seed=0,
                     progress=False)  # fmt: skip
    # Context pairs wide enough for 4 views on every test scene, so each count keeps every scene.
    index = json.loads((tmp_path / "src" / "evaluation_index.json").read_text())
    index = {key: {"context": [1, 10], "target": [4, 7], "overlap": 0.5} for key in index}
    (tmp_path / "index.json").write_text(json.dumps(index))
    shards = tmp_path / "shards"
    convert_dataset(tmp_path / "src", shards, size=SIZE, eval_index=tmp_path / "index.json", progress=False)
    run = tmp_path / "run"
    common = ["-c", "conf/smoke.yaml", "--data.root", str(shards), "--trainer.default_root_dir", str(run),
              "--trainer.enable_progress_bar", "false"]  # fmt: skip
    run_lightning(["fit", *common, "--model.net.view_aggregation", "pool", "--data.num_context_views", "[2,4]",
                   "--trainer.max_steps", "4", "--trainer.logger+=CSVLogger", "--trainer.logger.save_dir",
                   str(run), "--trainer.logger.name", "", "--trainer.logger.version", ""])  # fmt: skip
    with open(run / "metrics.csv") as f:
        logged = {int(r["step"]): int(float(r["train/context_views"])) for r in csv.DictReader(f)
                  if r["train/context_views"]}  # fmt: skip
    assert logged == {step: ContextCount(2, 4).at(0, step) for step in range(4)}  # data.seed 0
    assert len(set(logged.values())) > 1

    frames = {}
    for k in (2, 3, 4):
        # The run's own config; the checkpoint brings the pool head (model.net is read from it).
        last = str(run / "checkpoints" / "last.ckpt")
        run_lightning(["test", "-c", str(run / "config.yaml"), "--data.num_context_views", str(k),
                       "--trainer.logger", "false", "--ckpt_path", last])  # fmt: skip
        with open(run / "test-latest" / "per_scene.csv") as f:
            rows = list(csv.DictReader(f))
        assert {int(r["context_views"]) for r in rows} == {k} and len(rows) == len(index)
        for r in rows:
            context = [int(c) for c in r["context_frames"].split()]
            assert len(context) == k and context[0] == 1 and set(context) <= set(range(1, 11)) - {4, 7}
        frames[k] = {r["scene"]: r["target_frames"] for r in rows}
    assert frames[2] == frames[3] == frames[4] == {key: "4 7" for key in index}

    assert bench(["--ckpt", str(run / "checkpoints" / "last.ckpt"), "--knobs", "context_views",
                  "--context-views", "2,3,4,9", "--repeats", "1", "--warmup", "0", "--process-warmup", "0",
                  "--no-progress", "--out", str(tmp_path / "bench")]) == 0  # fmt: skip
    rows = {r["label"]: r for r in json.loads((tmp_path / "bench" / "bench.json").read_text())["rows"]}
    for k in (2, 3, 4):
        assert not rows[f"{k} views"]["skipped"] and rows[f"{k} views"]["gaussians"] == k * SIZE * SIZE
    assert "carry no 9-view context" in rows["9 views"]["skipped"]


def test_the_target_views_pose_errors_leave_the_other_context_views_out(tmp_path, monkeypatch):
    """rot_err_deg averages over every view but view 0, rot_err_target_deg over the target views alone: the
    same views at every count of context views."""
    module = _module("pool", tmp_path)
    batch = _batch(3, seed=0)  # views: context 0, 1, 2, then one target
    truth = torch.cat([batch.context.extrinsics, batch.target.extrinsics], dim=1)

    def turned(degrees: float) -> Tensor:  # a rotation about the camera's y axis
        a = torch.tensor(degrees).deg2rad()
        c, s = a.cos(), a.sin()
        return torch.tensor([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])

    predicted = truth.clone()
    predicted[:, 2] = predicted[:, 2] @ turned(30.0)  # the extra context view, 30° off
    predicted[:, 3] = predicted[:, 3] @ turned(10.0)  # the target, 10° off
    out = SimpleNamespace(extrinsics=predicted)
    rendered = SimpleNamespace(color=batch.target.images.float() / 255)
    monkeypatch.setattr(module, "forward", lambda *args, **kwargs: (out, rendered))
    metrics, _, _ = module._evaluate(batch)
    assert metrics["rot_err_deg"].tolist() == pytest.approx([40 / 3] * 2, abs=1e-3)  # views 1, 2, 3: 0, 30, 10
    assert metrics["rot_err_target_deg"].tolist() == pytest.approx([10.0] * 2, abs=1e-3)
