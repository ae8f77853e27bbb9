"""Chunk -> shard conversion: round trip, real field layout, skipped scenes, resumability, manifest."""

from __future__ import annotations

import importlib.util
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.data import DataModule, convert_dataset, verify_shards
from aesplat.data.stream import read_tar
from aesplat.data.synthetic_scenes import render_scene, sample_scene
from aesplat.geometry import project_points, unproject_depth

H, W = 48, 64  # landscape source: the centre crop keeps columns 8..56
SIZE = 32


def jpeg_tensor(image: np.ndarray, quality: int = 95) -> torch.Tensor:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=quality)
    return torch.tensor(list(buf.getvalue()), dtype=torch.uint8)


def chunk_entry(key: str, images: np.ndarray, c2w: np.ndarray, k: np.ndarray) -> dict:
    """A scene in the real pixelSplat field layout, built from plain tensors (independent of the library)."""
    w2c = np.linalg.inv(c2w)[:, :3, :]  # [F, 3, 4]
    f = len(images)
    rows = np.concatenate([k[:, [0, 1, 0, 1], [0, 1, 2, 2]], np.zeros((f, 2)), w2c.reshape(f, 12)], axis=1)
    return {
        "url": f"https://www.youtube.com/watch?v={key}",
        "timestamps": torch.arange(f, dtype=torch.int64) * 33_366_666,
        "cameras": torch.tensor(rows, dtype=torch.float32),
        "images": [jpeg_tensor(im) for im in images],
        "key": key,
    }


@pytest.fixture(scope="module")
def scene():
    s = sample_scene(21, frames=8, height=H, width=W, effects=("textures",))
    return s, render_scene(s, H, W)


def write_source(root: Path, train: list[dict], test: list[dict], evaluation: dict) -> None:
    for split, scenes in (("train", train), ("test", test)):
        (root / split).mkdir(parents=True)
        torch.save(scenes, root / split / "000000.torch")
        (root / split / "index.json").write_text(json.dumps({s["key"]: "000000.torch" for s in scenes}))
    (root / "evaluation_index.json").write_text(json.dumps(evaluation))


def test_round_trip_chunk_to_batch(tmp_path, scene):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w = s.extrinsics.double().numpy()
    k = s.intrinsics.double().expand(8, 3, 3).numpy()
    entry = chunk_entry("0a1b2c3d", images, c2w, k)
    evaluation = {"0a1b2c3d": {"context": [1, 6], "target": [2, 3, 5], "overlap": 0.5}}
    write_source(tmp_path / "src", [entry], [entry], evaluation)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=SIZE, min_gap=3, max_gap=6,
                               samples_per_scene=3, progress=False)  # fmt: skip
    assert manifest["splits"]["test"]["samples"] == 1 and manifest["splits"]["train"]["samples"] == 3

    dm = DataModule(root=str(tmp_path / "out"), image_size=SIZE, num_workers=0)
    batch = next(iter(dm.eval_dataset()))
    frames = [1, 6, 2, 3, 5]
    assert batch.scene == ["0a1b2c3d"] and batch.gap.tolist() == [5]
    assert batch.overlap.tolist() == [0.5]
    assert batch.context.index.tolist() == [[1, 6]] and batch.target.index.tolist() == [[2, 3, 5]]
    extr = torch.cat([batch.context.extrinsics, batch.target.extrinsics], 1)[0]
    intr = torch.cat([batch.context.intrinsics, batch.target.intrinsics], 1)[0]
    assert torch.allclose(extr, s.extrinsics[frames], atol=1e-5)
    assert batch.context.images.dtype == torch.uint8 and batch.context.images.shape == (1, 2, 3, SIZE, SIZE)

    # Images: the source frame's centre crop, resized, within the tolerance of one more JPEG generation.
    got = torch.cat([batch.context.images, batch.target.images], 1)[0].permute(0, 2, 3, 1).float()
    for v, f in enumerate(frames):
        source = Image.open(io.BytesIO(bytes(entry["images"][f].tolist())))
        expect = np.array(source.crop((8, 0, 56, 48)).resize((SIZE, SIZE), Image.Resampling.BICUBIC))
        error = (got[v] - torch.from_numpy(expect).float()).abs()
        assert error.mean() < 3.0 and error.max() < 40  # a crop one pixel off fails

    # Intrinsics: a 3D point lands on the same (cropped, scaled) pixel.
    pts = unproject_depth(r.depth[None, [1]], s.intrinsics.expand(1, 1, 3, 3), s.extrinsics[None, [1]])
    pts = pts.reshape(1, -1, 3)[:, ::37]
    uv_src, _, valid = project_points(pts, s.intrinsics.expand(1, 5, 3, 3), s.extrinsics[None, frames], H, W)
    uv_out, _, _ = project_points(pts, intr[None], extr[None], SIZE, SIZE)
    expected = torch.stack([(uv_src[..., 0] - 8) * SIZE / H, uv_src[..., 1] * SIZE / H], -1)
    assert valid.any()
    assert torch.allclose(uv_out[valid], expected[valid], atol=1e-3)

    # Training samples: gaps over the whole range (the smallest always present), targets between the context.
    train = list(read_tar(next((tmp_path / "out" / "train").glob("*.tar"))))
    gaps = []
    for key, raw in train:
        meta = json.loads(raw["meta.json"])
        c0, c1 = meta["context"]
        gaps.append(meta["gap"])
        assert c1 - c0 == meta["gap"] and 3 <= meta["gap"] <= 6
        assert all(c0 < t < c1 for t in meta["target"]) and len(meta["target"]) == 2 + (meta["gap"] > 3)
        cams = np.load(io.BytesIO(raw["extrinsics.npy"]))
        assert np.allclose(cams, c2w[meta["context"] + meta["target"]], atol=1e-5)
        assert key.startswith("0a1b2c3d_")
    assert min(gaps) == 3


def test_webdataset_reads_the_shards(synthetic_shards):
    import webdataset as wds

    shard = sorted((synthetic_shards / "test").glob("*.tar"))[0]
    sample = next(iter(wds.WebDataset(str(shard), shardshuffle=False)))
    assert {"ctx0.jpg", "ctx1.jpg", "tgt0.jpg", "extrinsics.npy", "intrinsics.npy", "meta.json"} <= set(sample)
    meta = json.loads(sample["meta.json"])
    assert set(meta) == {"scene", "dataset", "context", "target", "gap", "overlap"}
    assert meta["dataset"] == "synthetic"


def test_invalid_scenes_are_skipped_and_counted(tmp_path, scene):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w = s.extrinsics.double().numpy()
    k = s.intrinsics.double().expand(8, 3, 3).numpy().copy()
    good = chunk_entry("good", images, c2w, k)
    wrong_shape = chunk_entry("wrongshape", images, c2w, k)
    wrong_shape["images"][3] = jpeg_tensor(images[3][:, :40])
    wide_k = k.copy()
    wide_k[:, 0, 0] = 0.3  # horizontal FOV 2 atan(0.5 / 0.3) = 118 degrees
    wide = chunk_entry("wide", images, c2w, wide_k)
    still = c2w.copy()
    still[:, :3, 3] = c2w[0, :3, 3]
    static = chunk_entry("static", images, still, k)
    corrupt = chunk_entry("corrupt", images, c2w, k)
    corrupt["images"][2] = torch.tensor(list(b"not a jpeg at all"), dtype=torch.uint8)
    short = chunk_entry("short", images[:2], c2w[:2], k[:2])
    brief = chunk_entry("brief", images[:4], c2w[:4], k[:4])  # no context gap of 4 frames fits
    evaluation = {"good": {"context": [0, 7], "target": [3], "overlap": 0.4}, "wide": None, "absent": None,
                  "missing": {"context": [0, 2], "target": [1], "overlap": 0.9}}  # fmt: skip
    train = [good, wrong_shape, wide, static, corrupt, short, brief]
    test = [good, wide, chunk_entry("unindexed", images, c2w, k)]
    write_source(tmp_path / "src", train, test, evaluation)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=4, max_gap=7,
                               samples_per_scene=4, progress=False)  # fmt: skip
    tr, te = manifest["splits"]["train"], manifest["splits"]["test"]
    assert tr["skips"] == {"corrupt_image": 1, "degenerate_baseline": 1, "fov_too_wide": 1, "too_few_frames": 1,
                           "wrong_shape": 1, "shorter_than_min_gap": 1}  # fmt: skip
    assert tr["scenes"] == 1 and tr["scenes_seen"] == 7 and tr["samples"] == 4
    assert te["skips"] == {"fov_too_wide": 1, "not_in_evaluation_index": 1}
    assert te["samples"] == 1 and te["evaluation_index_missing"] == 1
    for split in ("train", "test"):
        for shard in manifest["splits"][split]["shards"]:
            assert len(shard["sha256"]) == 64

    # The same scenes pass when the limits allow them.
    loose = convert_dataset(tmp_path / "src", tmp_path / "out2", size=16, min_gap=2, max_gap=7, max_fov_deg=130,
                            progress=False)  # fmt: skip
    assert "fov_too_wide" not in loose["splits"]["train"]["skips"]
    strict = convert_dataset(tmp_path / "src", tmp_path / "out3", size=16, expect_shape=(H, W + 2),
                             progress=False)  # fmt: skip
    assert strict["splits"]["train"]["samples"] == 0


def test_conversion_resumes_and_verifies(tmp_path, synthetic_src):
    out = tmp_path / "out"
    first = convert_dataset(synthetic_src, out, size=16, workers=2, samples_per_scene=2, progress=False)
    shards = sorted((out / "train").glob("*.tar"))
    assert len(shards) >= 2 and verify_shards(out) == []
    stamps = {p.name: p.stat().st_mtime_ns for p in shards}
    shards[1].unlink()  # an interrupted run: one shard never finished
    (out / "train" / (shards[1].stem + ".tar.tmp")).write_bytes(b"partial")
    assert verify_shards(out) == [f"train/{shards[1].name}"]
    again = convert_dataset(synthetic_src, out, size=16, workers=2, samples_per_scene=2, progress=False)
    assert again["splits"] == first["splits"]
    assert shards[1].exists() and verify_shards(out) == []
    for p in shards[:1] + shards[2:]:
        assert p.stat().st_mtime_ns == stamps[p.name]  # finished shards were kept, not rewritten

    data = bytearray(shards[0].read_bytes())  # bit rot: the checksum catches it, a rerun repairs it
    data[600] ^= 0xFF
    shards[0].write_bytes(bytes(data))
    assert verify_shards(out) == [f"train/{shards[0].name}"]
    os.utime(shards[0])
    convert_dataset(synthetic_src, out, size=16, workers=1, samples_per_scene=2, progress=False)
    assert verify_shards(out) == []

    # Other options or another evaluation index: a different conversion, never a silent reuse.
    other = convert_dataset(synthetic_src, out, size=20, samples_per_scene=2, progress=False)
    assert other["config"]["size"] == 20
    index = json.loads((synthetic_src / "evaluation_index.json").read_text())
    index[sorted(index)[0]] = None
    changed = tmp_path / "index.json"
    changed.write_text(json.dumps(index))
    fewer = convert_dataset(
        synthetic_src, out, size=20, samples_per_scene=2, eval_index=changed, progress=False
    )
    assert fewer["splits"]["test"]["samples"] == other["splits"]["test"]["samples"] - 1
    assert fewer["splits"]["test"]["skips"] == {"not_in_evaluation_index": 1}


def test_command_line_scripts(tmp_path):
    root = Path(__file__).resolve().parents[2] / "data_prep"
    src, out = tmp_path / "src", tmp_path / "out"
    run = [sys.executable, str(root / "synthetic.py"), "--out", str(src), "--scenes", "2", "--test-scenes", "1",
           "--frames", "6", "--height", "16", "--width", "24", "--seed", "5"]  # fmt: skip
    subprocess.run(run, check=True, capture_output=True)
    assert (src / "train" / "index.json").exists() and (src / "evaluation_index.json").exists()
    convert = [sys.executable, str(root / "to_shards.py"), "--src", str(src), "--out", str(out), "--size", "14",
               "--workers", "2", "--samples-per-scene", "2"]  # fmt: skip
    done = subprocess.run(convert, check=True, capture_output=True, text=True)
    summary = json.loads(done.stdout)
    assert summary["train"]["samples"] == 4 and summary["test"]["samples"] == 1
    assert json.loads((out / "manifest.json").read_text())["config"]["size"] == 14
    spec = importlib.util.spec_from_file_location("to_shards", root / "to_shards.py")
    to_shards = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(to_shards)
    for damage, code in ((False, 0), (True, 1)):
        if damage:
            next((out / "test").glob("*.tar")).write_bytes(b"damaged")
        with pytest.raises(SystemExit) as verdict:
            to_shards.main(["--verify", "--out", str(out)])
        assert verdict.value.code == code
    # A folder without a manifest: one line, no traceback, nothing written.
    with pytest.raises(SystemExit) as verdict:
        to_shards.main(["--verify", "--out", str(tmp_path / "src")])
    assert str(verdict.value) == (
        f"to_shards.py: no manifest.json in {tmp_path / 'src'}: nothing to verify (convert first: to_shards.py "
        f"--src SRC --out {tmp_path / 'src'})"
    )


def test_unreadable_chunk_is_counted_named_and_writes_no_shard(tmp_path, scene, capsys):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    entry = chunk_entry(
        "fine", images, s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    )
    write_source(tmp_path / "src", [entry], [entry], {"fine": {"context": [0, 4], "target": [1, 2, 3]}})
    (tmp_path / "src" / "train" / "000001.torch").write_bytes(b"half a download")
    index = {"fine": "000000.torch", "lost": "000001.torch"}
    (tmp_path / "src" / "train" / "index.json").write_text(json.dumps(index))
    manifest = convert_dataset(
        tmp_path / "src", tmp_path / "out", size=16, min_gap=2, max_gap=6, progress=False
    )
    assert manifest["splits"]["train"]["skips"] == {"corrupt_chunk": 1}
    assert manifest["splits"]["train"]["samples"] == 8 and manifest["splits"]["test"]["samples"] == 1
    err = capsys.readouterr().err
    assert "to_shards: train/000001.torch: corrupt chunk, no shard written (cannot read chunk" in err
    assert sorted(p.name for p in (tmp_path / "out" / "train").iterdir()) == [
        "train-000000.json",
        "train-000000.tar",
    ]
    assert [s["chunk"] for s in manifest["splits"]["train"]["shards"]] == ["000000.torch"]
    assert verify_shards(tmp_path / "out") == []


def test_skipped_scenes_are_named_on_stderr(tmp_path, scene, capsys):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    fine = chunk_entry("fine", images, c2w, k)
    broken = chunk_entry("nan_camera", images, c2w, k)
    broken["cameras"][0, 0] = float("nan")
    write_source(tmp_path / "src", [fine, broken], [fine], {"fine": {"context": [0, 4], "target": [1, 2, 3]}})
    manifest = convert_dataset(
        tmp_path / "src", tmp_path / "out", size=16, min_gap=2, max_gap=6, progress=False
    )
    assert manifest["splits"]["train"]["skips"] == {"bad_camera": 1}
    err = capsys.readouterr().err
    assert "to_shards: train/000000.torch: scene nan_camera skipped (bad_camera)" in err
    assert "scene fine" not in err


def test_missing_source_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="train/ or test/"):
        convert_dataset(tmp_path, tmp_path / "out", progress=False)


def test_test_samples_carry_highlight_masks(tmp_path, scene):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    shiny, matte, old = (chunk_entry(name, images, c2w, k) for name in ("shiny", "matte", "old"))
    magnitude = torch.zeros(8, H, W, dtype=torch.float16)
    magnitude[3, 10:20, 20:30] = 0.5  # a highlight block in frame 3 (columns 12..22 of the centre crop)
    shiny["specular"] = magnitude
    matte["specular"] = torch.zeros(8, H, W, dtype=torch.float16)  # a diffuse scene: an empty mask
    evaluation = {
        name: {"context": [1, 6], "target": [2, 3, 5], "overlap": 0.5} for name in ("shiny", "matte", "old")
    }
    write_source(tmp_path / "src", [shiny], [shiny, matte, old], evaluation)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=3, max_gap=6,
                               specular_threshold=0.2, progress=False)  # fmt: skip

    samples = dict(read_tar(next((tmp_path / "out" / "test").glob("*.tar"))))
    masks = {}
    for name in ("shiny", "matte"):
        assert {f"tgt{i}.spec.png" for i in range(3)} <= set(samples[name])
        masks[name] = [np.array(Image.open(io.BytesIO(samples[name][f"tgt{i}.spec.png"]))) for i in range(3)]
    assert not any(n.endswith(".spec.png") for n in samples["old"])  # chunks without `specular` still convert
    # By hand: the 48-pixel crop shrinks 3x; a pixel is marked where the block's mean over it exceeds 0.2:
    # rows 3 and 6 hold 2/3 of a block row (mean 0.33), column 7 only 1/3 (0.17).
    expect = np.zeros((16, 16), np.uint8)
    expect[3:7, 4:7] = 255
    assert np.array_equal(masks["shiny"][1], expect)  # target 1 is frame 3
    assert not masks["shiny"][0].any() and not masks["shiny"][2].any()
    assert not any(m.any() for m in masks["matte"])
    assert manifest["splits"]["test"]["highlight_share"] == pytest.approx(12 / (6 * 16 * 16))
    for _, raw in read_tar(next((tmp_path / "out" / "train").glob("*.tar"))):  # training samples: no masks
        assert not any(n.endswith(".spec.png") for n in raw)
