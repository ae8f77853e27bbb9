"""Streaming: rank/worker splits, equal training lengths, corrupt data, curriculum, flips, resume."""

from __future__ import annotations

import io
import json
import logging
import shutil
from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from aesplat.data import DataModule, GapCurriculum, flip_views
from aesplat.data.shards import write_tar
from aesplat.data.stream import read_tar, sample_keys
from aesplat.data.synthetic_scenes import render_scene, sample_scene
from aesplat.geometry import project_points, unproject_depth

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


def test_training_shards_are_split_by_rank(synthetic_shards):
    split = []
    for rank in range(2):
        dm = module(synthetic_shards)
        dm.set_distributed(rank, 2)
        split.append(dm.train_dataset().worker_shards(0, 1))
    assert split[0] and split[1] and not set(split[0]) & set(split[1])


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
    corrupt_copy(synthetic_shards, tmp_path)
    shutil.copytree(tmp_path / "test", tmp_path / "train")
    dm = module(tmp_path, num_workers=2, train_batches_per_epoch=4, batch_size=1, gap_final=(1, 20),
                gap_initial=(1, 20))  # fmt: skip
    assert len(list(dm.train_dataloader())) == 4  # the stream keeps going around the bad data
    errors = dm.data_errors()
    assert errors["train/corrupt_shards"] >= 1 or errors["train/corrupt_samples"] >= 1


def test_curriculum_ranges():
    c = GapCurriculum(initial=(25, 25), final=(25, 90), warmup_steps=1000)
    assert c.allowed(0) == (25, 25) and c.allowed(500) == (25, 58) and c.allowed(1000) == (25, 90)
    assert c.allowed(10**9) == (25, 90) and c.accepts(40, 1000) and not c.accepts(40, 0)
    with pytest.raises(ValueError, match="lo <= hi"):
        GapCurriculum(initial=(30, 20))


def gaps_of(loader) -> set[int]:
    return {g for b in loader for g in b.gap.tolist()}


def test_stream_yields_only_gaps_allowed_at_the_step(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=100,
                train_batches_per_epoch=6, num_workers=2)  # fmt: skip
    loader = dm.train_dataloader()
    assert gaps_of(loader) <= {2, 3}
    dm.set_global_step(100)  # the persistent workers read the step from shared memory
    assert dm.allowed_gap() == (6, 8)
    assert gaps_of(loader) <= {6, 7, 8}
    dm.set_global_step(50)
    lo, hi = dm.allowed_gap()
    assert (lo, hi) == (4, 6) and gaps_of(loader) <= set(range(lo, hi + 1))
    assert dm.data_errors()["train/curriculum_skipped"] > 0


def test_samples_with_too_few_targets_are_passed_over(synthetic_shards):
    dm = module(synthetic_shards, num_target_views=2, train_batches_per_epoch=4)
    for b in dm.train_dataloader():  # gap-2 samples hold a single target
        assert b.target.images.shape[1] == 2
        assert torch.all(b.target.index[:, 0] < b.target.index[:, 1])
    assert dm.data_errors()["train/too_few_targets"] > 0 and dm.data_errors()["train/corrupt_samples"] == 0


def test_unsatisfiable_curriculum_is_a_clear_error(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(50, 60), gap_final=(50, 60))
    with pytest.raises(RuntimeError, match="curriculum"):
        next(iter(dm.train_dataloader()))


def test_state_dict_restores_the_curriculum(synthetic_shards):
    dm = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=100)
    dm.set_global_step(77)
    state = dm.state_dict()
    restored = module(synthetic_shards, gap_initial=(2, 3), gap_final=(6, 8), gap_warmup_steps=100)
    restored.load_state_dict(state)
    assert restored.global_step == 77 and restored.allowed_gap() == dm.allowed_gap()


def test_rank_and_step_come_from_the_trainer(synthetic_shards):
    dm = module(synthetic_shards)
    dm.trainer = SimpleNamespace(global_rank=1, world_size=3, global_step=12)
    dm.setup("fit")
    assert (dm.rank, dm.world_size, dm.global_step) == (1, 3, 12)
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
            frames = meta["context"] + meta["target"]
            cams = np.load(io.BytesIO(raw["extrinsics.npy"]))
            ks = np.load(io.BytesIO(raw["intrinsics.npy"]))
            for f, c, k in zip(frames, cams, ks):
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
    from aesplat.data.stream import StreamConfig, collate, decode_sample

    key, raw = next(read_tar(sorted((synthetic_shards / "test").glob("*.tar"))[0]))
    cfg = StreamConfig(image_size=SIZE, batch_size=2, num_target_views=None)
    with_mask = decode_sample(key, raw, cfg, None)
    bare = decode_sample(key, {k: v for k, v in raw.items() if not k.endswith(".spec.png")}, cfg, None)
    assert bare["highlight"] is None and collate([bare, bare], cfg).highlight is None
    assert collate([with_mask, with_mask], cfg).highlight.shape[:2] == (2, 3)
    with pytest.raises(ValueError, match="highlight masks"):
        collate([with_mask, bare], cfg)


def test_a_flipped_sample_flips_its_masks(synthetic_shards):
    from aesplat.data.stream import StreamConfig, decode_sample

    key, raw = next(read_tar(sorted((synthetic_shards / "test").glob("*.tar"))[0]))
    raw = dict(raw)
    raw["tgt0.spec.png"] = raw["tgt1.spec.png"] = raw["tgt2.spec.png"] = _png_left_half()
    flips = StreamConfig(image_size=SIZE, batch_size=1, num_target_views=3, flip_augment=True)
    seen = set()
    for seed in range(8):
        sample = decode_sample(key, raw, flips, np.random.default_rng(seed))
        plain = decode_sample(key, raw, StreamConfig(image_size=SIZE, batch_size=1, num_target_views=3), None)
        flipped = not torch.equal(sample["images"], plain["images"])
        assert torch.equal(sample["images"], plain["images"].flip(-1) if flipped else plain["images"])
        assert torch.equal(sample["highlight"], plain["highlight"].flip(-1) if flipped else plain["highlight"])
        seen.add(flipped)
    assert seen == {True, False}


def _png_left_half() -> bytes:
    from PIL import Image

    mask = np.zeros((SIZE, SIZE), np.uint8)
    mask[:, : SIZE // 2] = 255
    buf = io.BytesIO()
    Image.fromarray(mask).save(buf, format="PNG")
    return buf.getvalue()
