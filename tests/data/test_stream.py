"""Streaming: rank/worker splits, equal training lengths, corrupt data, the run-time view sampler and its
curriculum, counts of context views, exact resume, flips, old and foreign shards."""

from __future__ import annotations

import io
import json
import logging
import shutil
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from aesplat.data import DataModule, GapCurriculum, flip_views
from aesplat.data.decode import StreamConfig, collate, decode_evaluation_sample
from aesplat.data.synthetic_scenes import render_scene, sample_scene
from aesplat.data.tar_files import read_tar
from aesplat.errors import UserError
from aesplat.geometry import project_points, unproject_depth
from tests.helpers import sample_keys, write_tar

from .conftest import SIZE


def module(root, **kw) -> DataModule:
    args = dict(root=str(root), image_size=SIZE, batch_size=2, num_workers=0,
                gap_initial=(2, 8), gap_final=(2, 8), gap_warmup_steps=0, train_batches_per_epoch=3,
                flip_augment=False, shuffle_buffer=4)  # fmt: skip
    args.update(kw)
    return DataModule(**args)


def all_samples(folder) -> list[tuple[str, tuple[int, ...]]]:
    keys = []
    for shard in sorted(folder.glob("*.tar")):
        for _, raw in read_tar(shard):
            meta = json.loads(raw["meta.json"])
            keys.append((meta["scene"], tuple(meta["context"] + meta["target"])))
    return keys


def split_per_sample(src, dst) -> None:
    """One shard per sample: more shards than ranks x workers."""
    dst.mkdir()
    for shard in sorted(src.glob("*.tar")):
        for key, raw in read_tar(shard):
            write_tar(dst / f"{key}.tar", [(key, raw)])


@pytest.mark.parametrize("many_shards", [False, True], ids=["sample-split", "shard-split"])
def test_eval_two_ranks_two_workers_yield_each_sample_once(synthetic_shards, tmp_path, many_shards):
    root = synthetic_shards
    if many_shards:
        root = tmp_path
        split_per_sample(synthetic_shards / "test", tmp_path / "test")
    expected = all_samples(root / "test")
    shards = sorted((root / "test").glob("*.tar"))
    assert (len(shards) >= 4) == many_shards and len(expected) == 5
    seen = []
    for rank in range(2):
        dm = module(root, num_workers=2, eval_batch_size=2)
        dm.set_distributed(rank, 2)
        dm.setup("test")
        for batch in dm.test_dataloader():
            assert batch.target.images.shape[1] == 3  # every target of the evaluation index
            seen += sample_keys(batch)
    assert Counter(seen) == Counter(expected) and len(seen) == len(set(seen))


def test_reads_shards_written_by_webdataset(synthetic_shards, tmp_path):
    import webdataset as wds

    (tmp_path / "test").mkdir()
    source = list(read_tar(sorted((synthetic_shards / "test").glob("*.tar"))[0]))
    with wds.TarWriter(str(tmp_path / "test" / "other-000000.tar")) as sink:
        for key, raw in source:
            sink.write({"__key__": key, **raw})
    batches = list(module(tmp_path).test_dataloader())
    assert [k for b in batches for k in b.scene] == [json.loads(raw["meta.json"])["scene"] for _, raw in source]


def test_eval_is_deterministic(synthetic_shards):
    runs = []
    for _ in range(2):
        dm = module(synthetic_shards, num_workers=2)
        runs.append([(sample_keys(b), b.context.images.clone()) for b in dm.test_dataloader()])
    assert [k for k, _ in runs[0]] == [k for k, _ in runs[1]]
    assert all(torch.equal(a, b) for (_, a), (_, b) in zip(runs[0], runs[1]))


def test_training_streams_yield_equal_batches_per_rank(synthetic_shards):
    assert len(list((synthetic_shards / "train").glob("*.tar"))) == 3  # uneven over 2 ranks
    for rank in range(2):
        dm = module(synthetic_shards, num_workers=2, train_batches_per_epoch=5)
        dm.set_distributed(rank, 2)
        loader = dm.train_dataloader()
        assert len(loader) == 5
        for _ in range(2):  # a second epoch on the persistent workers
            batches = list(loader)
            assert len(batches) == 5
            for b in batches:
                assert b.context.images.shape == (2, 2, 3, SIZE, SIZE)
                assert b.target.images.shape == (2, 1, 3, SIZE, SIZE)
                assert b.context.images.dtype == torch.uint8
                c0, c1 = b.context.index.unbind(-1)
                assert torch.all((b.target.index[:, 0] > c0) & (b.target.index[:, 0] < c1))
                assert torch.equal(b.gap, c1 - c0)


def test_training_scenes_are_split_by_rank_and_worker(synthetic_shards):
    split = []
    for rank in range(2):
        dm = module(synthetic_shards)
        dm.set_distributed(rank, 2)
        stream = dm.train_dataset()
        split.append({s.key for s in stream.scenes})
        workers = [{s.key for s in stream.worker_scenes(role, 2)} for role in range(2)]
        assert (
            workers[0] and workers[1] and not workers[0] & workers[1] and workers[0] | workers[1] == split[-1]
        )
    assert split[0] and split[1] and not split[0] & split[1] and len(split[0] | split[1]) == 6


def corrupt_copy(src, dst):
    """Test shards with one truncated shard and one sample whose JPEG is garbage."""
    shutil.copytree(src / "test", dst / "test")
    shards = sorted((dst / "test").glob("*.tar"))
    data = shards[0].read_bytes()
    shards[0].write_bytes(data[: len(data) // 2 + 100])
    samples = list(read_tar(shards[1]))
    samples[0][1]["ctx1.jpg"] = b"\xff\xd8 this is not a JPEG"
    write_tar(shards[1], samples)
    return len(list(read_tar(shards[1])))


def test_corrupt_shard_and_sample_are_skipped_counted_and_logged(synthetic_shards, tmp_path, caplog):
    corrupt_copy(synthetic_shards, tmp_path)
    dm = module(tmp_path)
    with caplog.at_level(logging.WARNING, logger="aesplat.data"):
        keys = [k for b in dm.test_dataloader() for k in sample_keys(b)]
    full = all_samples(synthetic_shards / "test")
    assert set(keys) < set(full) and len(keys) == len(set(keys))
    assert len(keys) >= len(full) - 3  # the truncated shard's second sample and the garbage sample
    errors = dm.data_errors()
    assert errors["test/corrupt_shards"] == 1 and errors["test/corrupt_samples"] == 1
    messages = " ".join(r.getMessage() for r in caplog.records)
    assert "corrupt shard" in messages and "corrupt sample" in messages


def test_corrupt_data_counters_reach_the_main_process_from_workers(synthetic_shards, tmp_path):
    shutil.copytree(synthetic_shards, tmp_path / "shards")
    shards = sorted((tmp_path / "shards" / "train").glob("*.tar"))
    data = shards[0].read_bytes()
    shards[0].write_bytes(data[: len(data) // 2 + 100])  # truncated after its first scene
    scenes = list(read_tar(shards[1]))
    blob = scenes[0][1]["frames.jpgs"]  # every frame of its first scene is garbage
    scenes[0][1]["frames.jpgs"] = bytes(len(blob))
    write_tar(shards[1], scenes)
    dm = module(tmp_path / "shards", num_workers=2, train_batches_per_epoch=12, batch_size=1)
    assert len(list(dm.train_dataloader())) == 12  # the stream keeps going around the bad data
    errors = dm.data_errors()
    assert errors["train/corrupt_shards"] >= 1 and errors["train/corrupt_samples"] >= 1


def test_curriculum_ranges():
    c = GapCurriculum(initial=(25, 25), final=(25, 90), warmup_steps=1000)
    assert c.allowed(0) == (25, 25) and c.allowed(500) == (25, 58) and c.allowed(1000) == (25, 90)
    assert c.allowed(10**9) == (25, 90) and c.accepts(40, 1000) and not c.accepts(40, 0)
    with pytest.raises(ValueError, match="lo <= hi"):
        GapCurriculum(initial=(30, 20))


def gaps_of(loader) -> list[int]:
    return [g for b in loader for g in b.gap.tolist()]


def test_sampled_gaps_follow_the_curriculum_at_several_steps(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 14), gap_warmup_steps=1000, batch_size=8,
                train_batches_per_epoch=12, num_workers=2)  # fmt: skip
    loader = dm.train_dataloader()
    for start, (lo, hi) in ((0, (2, 3)), (504, (4, 9)), (1008, (6, 14)), (12 * 10**5, (6, 14))):
        dm.step_tracker.set(start)  # the persistent workers read the step from shared memory
        assert dm.curriculum.allowed(dm.step_tracker.get()) == (lo, hi)
        gaps = []
        for step, b in enumerate(loader, start):
            allowed = dm.curriculum.allowed(step)  # each batch is drawn for the step it is trained at
            assert all(allowed[0] <= g <= min(allowed[1], 11) for g in b.gap.tolist())  # 12 frames: at most 11
            gaps += b.gap.tolist()
        assert set(gaps) == set(range(lo, min(hi, 11) + 1)), (start, sorted(set(gaps)))  # both bounds reached
        assert max(Counter(gaps).values()) < 0.6 * len(gaps)  # not degenerate
    assert dm.data_errors()["train/scene_too_short"] == 0


def test_batches_drawn_after_a_step_change_follow_the_step_they_are_trained_at(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(2, 2), gap_final=(9, 9), gap_warmup_steps=6, batch_size=2,
                train_batches_per_epoch=6)  # fmt: skip
    for b, step in zip(dm.train_dataloader(), range(6)):
        assert set(b.gap.tolist()) == {dm.curriculum.allowed(step)[0]}


@pytest.mark.parametrize("count", [2, 3, 4, 5, 6])
def test_k_context_views_in_batches(synthetic_shards, count):
    dm = module(synthetic_shards, num_context_views=count, num_target_views=2, gap_initial=(2, 11),
                gap_final=(2, 11), train_batches_per_epoch=6, batch_size=3)  # fmt: skip
    for b in dm.train_dataloader():
        ctx, tgt = b.context.index, b.target.index
        assert ctx.shape == (3, count) and tgt.shape == (3, 2) and b.context.images.shape[1] == count
        assert torch.all(ctx[:, 1:] > ctx[:, :-1]) and torch.all(ctx >= 0) and torch.all(ctx < 12)
        assert torch.all((tgt > ctx[:, :1]) & (tgt < ctx[:, -1:])) and torch.all(tgt[:, 1] > tgt[:, 0])
        assert not any(set(t) & set(c) for t, c in zip(tgt.tolist(), ctx.tolist()))


def test_a_range_of_counts_draws_one_count_per_batch_from_seed_and_step(synthetic_shards):
    dm = module(synthetic_shards, num_context_views=(2, 5), gap_initial=(2, 11), gap_final=(2, 11),
                train_batches_per_epoch=24, num_workers=2)  # fmt: skip
    assert dm.num_context_views == (2, 5)  # as given, for the model to check its appearance head against
    counts = [b.context.num_views for b in dm.train_dataloader()]
    assert counts == [dm.context_views.at(dm.seed, step) for step in range(24)] and set(counts) == {2, 3, 4, 5}


def test_scenes_too_short_or_too_tight_are_skipped_counted_and_named(tmp_path, caplog):
    from aesplat.data import convert_dataset, generate_dataset

    for frames, seed in ((6, 1), (14, 2)):
        generate_dataset(
            tmp_path / f"src{frames}",
            scenes=2,
            test_scenes=1,
            val_scenes=0,
            frames=frames,
            height=16,
            width=24,
            seed=seed,
            scenes_per_chunk=2,
        )
    (tmp_path / "src6" / "train" / "000000.torch").rename(tmp_path / "src14" / "train" / "000009.torch")
    index = json.loads((tmp_path / "src14" / "train" / "index.json").read_text())
    index.update(
        {k: "000009.torch" for k in json.loads((tmp_path / "src6" / "train" / "index.json").read_text())}
    )
    (tmp_path / "src14" / "train" / "index.json").write_text(json.dumps(index))
    convert_dataset(tmp_path / "src14", tmp_path / "out", size=16, min_gap=2, progress=False)
    dm = module(tmp_path / "out", image_size=16, gap_initial=(7, 12), gap_final=(7, 12), batch_size=2,
                train_batches_per_epoch=6)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="aesplat.data"):
        gaps = gaps_of(dm.train_dataloader())
    assert min(gaps) >= 7 and max(gaps) <= 12
    assert dm.data_errors()["train/scene_too_short"] > 0  # 6-frame scenes: no gap of 7
    assert "skipping scene train001_00000 (6 frames)" in caplog.text and "scene_too_short" in caplog.text
    # Long enough for the gap, too few frames between for 4 context and 3 target views (they need a gap of 6).
    caplog.clear()
    tight = module(tmp_path / "out", image_size=16, gap_initial=(5, 6), gap_final=(5, 6), num_context_views=4,
                   num_target_views=3, batch_size=2, train_batches_per_epoch=6)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="aesplat.data"):
        assert set(gaps_of(tight.train_dataloader())) == {6}
    assert (
        tight.data_errors()["train/too_few_between"] > 0 and tight.data_errors()["train/scene_too_short"] == 0
    )
    assert "(6 frames) at step" in caplog.text and "too_few_between" in caplog.text


def test_a_split_with_no_usable_scene_is_one_line(synthetic_shards):
    for options, where in (
        ({"gap_initial": (50, 60), "gap_final": (50, 60)}, "at step 0"),
        ({"gap_initial": (2, 8), "gap_final": (20, 30), "gap_warmup_steps": 160}, "at step 90"),
        ({"num_context_views": 6, "num_target_views": 6}, "at step 0"),
    ):
        with pytest.raises(UserError, match=f"no training scene in .* gives an example {where}") as err:
            module(synthetic_shards, **options).train_dataloader()
        assert "\n" not in str(err.value) and "scenes have 12..12 frames" in str(err.value)


def test_resume_mid_epoch_draws_the_same_views_as_an_uninterrupted_run(synthetic_shards):
    def run(step: int, workers: int) -> list[tuple]:
        dm = module(synthetic_shards, num_workers=workers, train_batches_per_epoch=8, num_context_views=(2, 3),
                    gap_initial=(2, 4), gap_final=(4, 11), gap_warmup_steps=10, flip_augment=True)  # fmt: skip
        dm.step_tracker.set(step)
        return [(sample_keys(b), b.context.images.clone(), b.context.extrinsics.clone()) for b in
                dm.train_dataloader()]  # fmt: skip

    for workers in (0, 2):
        whole = run(8, workers)  # the second epoch (steps 8..15), uninterrupted
        resumed = run(11, workers)  # stopped after step 10, resumed at 11
        assert len(whole) == 8 and len(resumed) == 5
        for (keys, images, extr), (keys_r, images_r, extr_r) in zip(whole[3:], resumed):
            assert keys == keys_r and torch.equal(images, images_r) and torch.equal(extr, extr_r)
    assert [k for k, _, _ in run(8, 0)] != [k for k, _, _ in run(0, 0)]  # another epoch, other views


def test_examples_per_scene_reads_each_scene_once_for_several_examples(synthetic_shards, monkeypatch):
    from aesplat.data import stream

    reads = []
    real = stream.index_scenes

    def counting(path):
        for entry in real(path):
            reads.append(entry.key)
            yield entry

    monkeypatch.setattr(stream, "index_scenes", counting)
    drawn = {}
    for per_scene in (1, 4):
        reads.clear()
        dm = module(synthetic_shards, examples_per_scene=per_scene, batch_size=4, train_batches_per_epoch=12,
                    shuffle_buffer=8, gap_initial=(2, 11), gap_final=(2, 11))  # fmt: skip
        drawn[per_scene] = [k for b in dm.train_dataloader() for k in sample_keys(b)]
        assert len(drawn[per_scene]) == 48
        ratio = len(drawn[per_scene]) / len(reads)
        assert (0.8 <= ratio <= 1.2) if per_scene == 1 else ratio > 2.5, (per_scene, ratio)
    assert len(set(drawn[4])) > 0.8 * len(drawn[4])  # the examples of one read differ in their views


def test_a_fixed_pool_reuses_few_examples_per_scene(synthetic_shards):
    def contexts(**options) -> dict[str, set]:
        dm = module(synthetic_shards, batch_size=4, train_batches_per_epoch=30, **options)
        seen: dict[str, set] = {}
        for b in dm.train_dataloader():
            for scene, ctx in zip(b.scene, b.context.index.tolist()):
                seen.setdefault(scene, set()).add(tuple(ctx))
        return seen

    pooled, fresh = contexts(fixed_pool=2), contexts()
    assert all(len(c) <= 2 for c in pooled.values()) and len(pooled) == 6
    assert max(len(c) for c in fresh.values()) > 4
    # The first phase of the curriculum allows only the pool's smallest-gap member: one example per scene.
    early = contexts(fixed_pool=8, gap_initial=(2, 2), gap_final=(2, 8), gap_warmup_steps=10**6)
    assert all(len(c) == 1 and next(iter(c))[1] - next(iter(c))[0] == 2 for c in early.values())
    with pytest.raises(UserError, match="fixed_pool draws its examples once"):
        module(synthetic_shards, fixed_pool=2, num_context_views=(2, 3))


def test_state_dict_restores_the_curriculum(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=100)
    dm.step_tracker.set(77)
    state = dm.state_dict()
    restored = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=100)
    restored.load_state_dict(state)
    assert restored.step_tracker.get() == 77 and restored.curriculum.allowed(77) == dm.curriculum.allowed(77)


def test_rank_and_step_come_from_the_trainer(synthetic_shards):
    dm = module(synthetic_shards)
    dm.trainer = SimpleNamespace(global_rank=1, world_size=3, global_step=12)
    dm.setup("fit")
    assert (dm.rank, dm.world_size, dm.step_tracker.get()) == (1, 3, 12)
    assert dm.train_dataset().rank == 1


def test_missing_shards_name_the_fix(tmp_path):
    with pytest.raises(FileNotFoundError, match="to_shards.py"):
        module(tmp_path).train_dataloader()


def test_resize_to_another_image_size_keeps_intrinsics(synthetic_shards):
    small = next(iter(module(synthetic_shards).test_dataloader()))
    big = next(iter(module(synthetic_shards, image_size=42).test_dataloader()))
    assert big.context.images.shape[-2:] == (42, 42)
    assert torch.equal(big.context.intrinsics, small.context.intrinsics)


def test_flip_keeps_projections_consistent():
    h, w = 24, 32
    scene = sample_scene(3, frames=6, height=h, width=w, effects=("textures",))
    out = render_scene(scene, h, w, frames=[0, 5])
    images = out.images.permute(0, 3, 1, 2)  # [2, 3, H, W]
    extr, intr = scene.extrinsics[[0, 5]], scene.intrinsics.expand(2, 3, 3)
    f_images, f_extr, f_intr = flip_views(images, extr, intr)
    pts = unproject_depth(out.depth[None, :1], intr[None, :1], extr[None, :1]).reshape(1, -1, 3)[:, ::7]
    uv, z, valid = project_points(pts, intr[None], extr[None], h, w)
    mirrored = pts * torch.tensor([-1.0, 1.0, 1.0])
    f_uv, f_z, f_valid = project_points(mirrored, f_intr[None], f_extr[None], h, w)
    assert torch.allclose(f_uv[..., 0], w - uv[..., 0], atol=1e-3)
    assert torch.allclose(f_uv[..., 1], uv[..., 1], atol=1e-3) and torch.allclose(f_z, z, atol=1e-4)
    assert torch.equal(f_valid, valid)
    # The flipped image shows at the flipped pixel what the original shows at the original pixel.
    col, row = uv[0, 1, valid[0, 1], 0].long().clamp(0, w - 1), uv[0, 1, valid[0, 1], 1].long().clamp(0, h - 1)
    assert torch.equal(f_images[1][:, row, w - 1 - col], images[1][:, row, col])
    assert torch.allclose(torch.linalg.det(f_extr[:, :3, :3]), torch.ones(2))  # still rotations
    again = flip_views(f_images, f_extr, f_intr)
    assert torch.equal(again[0], images) and torch.allclose(again[1], extr) and torch.allclose(again[2], intr)


def test_flip_augment_flips_some_training_samples_consistently(synthetic_shards):
    source = {}
    for shard in sorted((synthetic_shards / "train").glob("*.tar")):
        for _, raw in read_tar(shard):
            meta = json.loads(raw["meta.json"])
            cams = np.load(io.BytesIO(raw["extrinsics.npy"]))
            ks = np.load(io.BytesIO(raw["intrinsics.npy"]))
            for f, c, k in zip(meta["frames"], cams, ks):
                source[(meta["scene"], f)] = (torch.from_numpy(c), torch.from_numpy(k))
    reflect = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    flipped = plain = 0
    dm = module(synthetic_shards, flip_augment=True, train_batches_per_epoch=8)
    for b in dm.train_dataloader():
        for i, scene in enumerate(b.scene):
            e, k = b.context.extrinsics[i, 1], b.context.intrinsics[i, 1]
            orig_e, orig_k = source[(scene, int(b.context.index[i, 1]))]
            if torch.allclose(e, orig_e, atol=1e-6):
                assert torch.allclose(k, orig_k)
                plain += 1
            else:
                assert torch.allclose(e, reflect @ orig_e @ reflect, atol=1e-6)
                assert torch.isclose(k[0, 2], 1 - orig_k[0, 2]) and torch.isclose(k[1, 2], orig_k[1, 2])
                flipped += 1
    assert flipped > 0 and plain > 0


def _masks(raw: dict, count: int) -> torch.Tensor:
    """The sample's target masks as written by to_shards: bool [count, 1, S, S]."""
    from PIL import Image

    return torch.stack([torch.from_numpy(np.array(Image.open(io.BytesIO(raw[f"tgt{i}.spec.png"]))) > 0)[None]
                        for i in range(count)])  # fmt: skip


def test_eval_batches_carry_the_highlight_masks(synthetic_shards):
    raw = {json.loads(r["meta.json"])["scene"]: r for s in sorted((synthetic_shards / "test").glob("*.tar"))
           for _, r in read_tar(s)}  # fmt: skip
    lit = 0
    for batch in module(synthetic_shards, eval_batch_size=1).test_dataloader():
        vt = batch.target.num_views
        assert batch.highlight.dtype == torch.bool and batch.highlight.shape == (1, vt, 1, SIZE, SIZE)
        assert torch.equal(batch.highlight[0], _masks(raw[batch.scene[0]], vt))
        lit += int(batch.highlight.any())
    assert lit > 0  # the fixture's scenes declare `specular` at random: some masks are not empty
    # Another image size: the masks are resized by nearest neighbour, like a mask should be.
    big = next(iter(module(synthetic_shards, image_size=2 * SIZE).test_dataloader()))
    small = next(iter(module(synthetic_shards).test_dataloader()))
    assert torch.equal(big.highlight, small.highlight.repeat_interleave(2, -1).repeat_interleave(2, -2))


def test_highlight_is_none_without_masks_and_mixed_batches_are_an_error(synthetic_shards, tmp_path):
    key, raw = next(read_tar(sorted((synthetic_shards / "test").glob("*.tar"))[0]))
    cfg = StreamConfig(image_size=SIZE, batch_size=2, num_target_views=None)
    with_mask = decode_evaluation_sample(raw, cfg)
    bare = decode_evaluation_sample({k: v for k, v in raw.items() if not k.endswith(".spec.png")}, cfg)
    assert bare.highlight is None and collate([bare, bare]).highlight is None
    assert collate([with_mask, with_mask]).highlight.shape[:2] == (2, 3)
    with pytest.raises(ValueError, match="highlight masks"):
        collate([with_mask, bare])


def test_eval_batches_group_samples_by_their_number_of_targets(synthetic_shards, tmp_path):
    """Two of the five samples carry 2 targets, the others 3: with eval_batch_size 2 each sample is evaluated
    once, in batches of one count (before, the first mixed batch stopped the evaluation)."""
    shutil.copytree(synthetic_shards, tmp_path / "shards")
    root = tmp_path / "shards"
    shortened, seen = set(), 0
    for shard in sorted((root / "test").glob("*.tar")):
        samples = []
        for key, raw in read_tar(shard):
            seen += 1
            if seen in (2, 3):  # the first batch mixes 3 and 2 targets
                meta = json.loads(raw["meta.json"])
                row = len(meta["context"]) + 2  # camera rows: context, targets, extra frames
                meta["target"] = meta["target"][:2]
                raw = {k: v for k, v in raw.items() if not k.startswith("tgt2.")}
                raw["meta.json"] = json.dumps(meta).encode()
                for name in ("extrinsics.npy", "intrinsics.npy"):
                    out = io.BytesIO()
                    np.save(out, np.delete(np.load(io.BytesIO(raw[name])), row, axis=0))
                    raw[name] = out.getvalue()
                shortened.add(meta["scene"])
            samples.append((key, raw))
        write_tar(shard, samples)
    targets = {}
    for batch in module(root, eval_batch_size=2).test_dataloader():
        for scene in batch.scene:
            assert scene not in targets
            targets[scene] = batch.target.num_views
    assert len(targets) == 5 and {s for s, n in targets.items() if n == 2} == shortened
    assert set(targets.values()) == {2, 3}


# ------------------------------------------------------------------------------------- old and foreign shards


def old_layout_copy(src, dst) -> None:
    """The shards as the conversion wrote them before training drew its views at run time: manifest version 1,
    every split of pre-drawn samples (ctx0, ctx1, tgt0..., meta without extra contexts)."""
    dst.mkdir()
    manifest = json.loads((src / "manifest.json").read_text())
    manifest["version"] = 1
    for split, entry in manifest["splits"].items():
        for key in ("layout", "context_views", "evaluation_samples", "frames"):
            entry.pop(key, None)
        (dst / split).mkdir()
        for shard in entry["shards"]:
            samples = []
            for key, raw in read_tar(src / split / shard["shard"]):
                meta = json.loads(raw["meta.json"])
                if split == "train":  # one pre-drawn sample per scene: frames 0, 4 and 2 between
                    frames = [0, 4, 2]
                    cams = [np.load(io.BytesIO(raw[n]))[frames] for n in ("extrinsics.npy", "intrinsics.npy")]
                    at = np.load(io.BytesIO(raw["frames.offsets.npy"]))
                    jpeg = [raw["frames.jpgs"][at[f] : at[f + 1]] for f in frames]
                    raw = {
                        "ctx0.jpg": jpeg[0],
                        "ctx1.jpg": jpeg[1],
                        "tgt0.jpg": jpeg[2],
                        "extrinsics.npy": _npy(cams[0]),
                        "intrinsics.npy": _npy(cams[1]),
                    }
                    meta = {
                        "scene": meta["scene"],
                        "dataset": meta["dataset"],
                        "context": [0, 4],
                        "target": [2],
                        "gap": 4,
                        "overlap": None,
                    }
                else:
                    n = len(meta["context"]) + len(meta["target"])
                    raw = {k: v for k, v in raw.items() if not k.startswith("xtr")}
                    raw["extrinsics.npy"] = _npy(np.load(io.BytesIO(raw["extrinsics.npy"]))[:n])
                    raw["intrinsics.npy"] = _npy(np.load(io.BytesIO(raw["intrinsics.npy"]))[:n])
                    meta = {k: meta[k] for k in ("scene", "dataset", "context", "target", "gap", "overlap")}
                samples.append(
                    (f"{key}_000" if split == "train" else key, {**raw, "meta.json": json.dumps(meta).encode()})
                )
            write_tar(dst / split / shard["shard"], samples)
    (dst / "manifest.json").write_text(json.dumps(manifest))


def _npy(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_old_sample_shards_still_evaluate_and_are_refused_for_training_with_the_command(
    synthetic_shards, tmp_path
):
    old = tmp_path / "old"
    old_layout_copy(synthetic_shards, old)
    dm = module(old)
    with pytest.raises(UserError) as err:
        dm.train_dataloader()
    message = str(err.value)
    assert "pre-drawn samples (manifest version 1)" in message and "\n" not in message
    assert f"python data_prep/to_shards.py --src {json.loads((old / 'manifest.json').read_text())['source']} " \
        f"--out {old} --size {SIZE}" in message  # fmt: skip
    new = [(sample_keys(b), b.target.images) for b in module(synthetic_shards).test_dataloader()]
    old_batches = [(sample_keys(b), b.target.images) for b in module(old).test_dataloader()]
    assert len(old_batches) == len(new)
    for (keys, images), (keys_old, images_old) in zip(new, old_batches):
        assert keys == keys_old and torch.equal(images, images_old)  # the same test figures as before
    with pytest.raises(UserError, match="carry contexts of up to 2 views, not 3"):
        module(old, eval_num_context_views=3).test_dataloader()


def test_tars_that_are_not_shards_are_refused(tmp_path):
    import tarfile

    (tmp_path / "test").mkdir()
    with tarfile.open(tmp_path / "test" / "photos.tar", "w") as tar:
        data = b"\xff\xd8 holiday"
        info = tarfile.TarInfo("holiday/beach.jpg")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    with pytest.raises(
        UserError, match="photos.tar is not a shard of aesplat .its first sample beach has no meta"
    ):
        module(tmp_path).test_dataloader()
    from aesplat import cli

    with pytest.raises(SystemExit) as verdict:  # `aesplat test` says so in one line instead of 0 scenes
        cli.main(
            [
                "test",
                "-c",
                str(Path(__file__).resolve().parents[2] / "conf" / "smoke.yaml"),
                "--data.root",
                str(tmp_path),
                "--trainer.default_root_dir",
                str(tmp_path / "run"),
            ]
        )
    assert str(verdict.value).startswith("aesplat test: ") and "is not a shard of aesplat" in str(verdict.value)
    assert "\n" not in str(verdict.value) and not (tmp_path / "run").exists()
    (tmp_path / "test" / "photos.tar").write_bytes(b"not a tar at all" * 100)
    with pytest.raises(UserError, match="not a readable tar archive"):
        module(tmp_path).test_dataloader()


def test_ddp_ranks_never_draw_the_same_scene_in_an_epoch(synthetic_shards, tmp_path):
    """Two gloo processes, each building its rank's stream as under a DDP Trainer: their scenes are disjoint."""
    import torch.multiprocessing as mp

    mp.spawn(_ddp_rank, args=(str(synthetic_shards), str(tmp_path)), nprocs=2, join=True)
    seen = [set(json.loads((tmp_path / f"rank{r}.json").read_text())) for r in range(2)]
    assert seen[0] and seen[1] and not seen[0] & seen[1]


def _ddp_rank(rank: int, root: str, out: str) -> None:
    import os

    import torch.distributed as dist

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(29500 + os.getppid() % 1000))
    dist.init_process_group("gloo", rank=rank, world_size=2)
    try:
        dm = module(root, num_workers=2, train_batches_per_epoch=6, batch_size=3)
        dm.trainer = SimpleNamespace(
            global_rank=dist.get_rank(), world_size=dist.get_world_size(), global_step=0
        )
        dm.setup("fit")
        scenes = [s for b in dm.train_dataloader() for s in b.scene]
        gathered: list = [None, None]
        dist.all_gather_object(gathered, scenes)
        assert len(gathered[1 - rank]) == len(scenes) == 18  # every rank the same number of batches
        Path(out, f"rank{rank}.json").write_text(json.dumps(sorted(set(scenes))))
    finally:
        dist.destroy_process_group()


def test_eval_transfer_scale_adds_the_targets_at_twice_the_size(synthetic_shards):
    """The ground truth of the resolution-transfer metric: every target decoded from the shard at s times the
    model's size, the same images a run at that size reads."""
    half = SIZE // 2
    batch = next(iter(module(synthetic_shards, image_size=half, eval_transfer_scale=2).test_dataloader()))
    full = next(iter(module(synthetic_shards).test_dataloader()))
    assert batch.target.images.shape[-2:] == (half, half)
    assert batch.target_large.shape == full.target.images.shape
    assert torch.equal(batch.target_large, full.target.images)
    assert torch.equal(batch.float_images().target_large, full.float_images().target.images)
    assert next(iter(module(synthetic_shards).test_dataloader())).target_large is None


def test_eval_transfer_scale_needs_shards_that_large(synthetic_shards):
    with pytest.raises(UserError, match=rf"at least {2 * SIZE}px.*holds images {SIZE}px.*--size {2 * SIZE}"):
        module(synthetic_shards, eval_transfer_scale=2).test_dataloader()


def test_test_split_scores_the_validation_scenes_when_asked(synthetic_shards):
    scenes = {s for b in module(synthetic_shards, test_split="validation").test_dataloader() for s in b.scene}
    tested = {s for b in module(synthetic_shards).test_dataloader() for s in b.scene}
    validation = {s for b in module(synthetic_shards).val_dataloader() for s in b.scene}
    assert scenes == validation and scenes.isdisjoint(tested)
    with pytest.raises(UserError, match="test_split"):
        module(synthetic_shards, test_split="train")
