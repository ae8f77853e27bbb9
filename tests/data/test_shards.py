"""Chunk -> shard conversion: round trip, real field layout, skipped scenes, resumability, manifest, and what a
careless or hostile input does (changed sources, a full disk, damaged manifests and indices, old shards)."""

from __future__ import annotations

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
from aesplat.data.synthetic_scenes import render_scene, sample_scene
from aesplat.data.tar_files import read_tar
from aesplat.errors import UserError
from aesplat.geometry import project_points, unproject_depth
from tests.helpers import ODD_KEYS, sample_keys
from tests.script_loader import DATA_PREP, load_script

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
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=SIZE, min_gap=3, progress=False)
    assert manifest["version"] == 2 and manifest["splits"]["train"]["layout"] == "scenes"
    assert manifest["splits"]["test"]["samples"] == 1 and manifest["splits"]["train"]["samples"] == 1
    assert manifest["splits"]["train"]["frames"] == 8

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
        error = (got[v] - torch.from_numpy(expected_crop(entry, f)).float()).abs()
        assert error.mean() < 3.0 and error.max() < 40  # a crop one pixel off fails

    # Intrinsics: a 3D point lands on the same (cropped, scaled) pixel.
    pts = unproject_depth(r.depth[None, [1]], s.intrinsics.expand(1, 1, 3, 3), s.extrinsics[None, [1]])
    pts = pts.reshape(1, -1, 3)[:, ::37]
    uv_src, _, valid = project_points(pts, s.intrinsics.expand(1, 5, 3, 3), s.extrinsics[None, frames], H, W)
    uv_out, _, _ = project_points(pts, intr[None], extr[None], SIZE, SIZE)
    expected = torch.stack([(uv_src[..., 0] - 8) * SIZE / H, uv_src[..., 1] * SIZE / H], -1)
    assert valid.any()
    assert torch.allclose(uv_out[valid], expected[valid], atol=1e-3)

    # The training shard holds the whole scene: every frame, its camera and the cropped intrinsics.
    (key, raw), *rest = list(read_tar(next((tmp_path / "out" / "train").glob("*.tar"))))
    assert key == "0a1b2c3d" and rest == [] and next(iter(raw)) == "meta.json"  # meta first: cheap to probe
    meta = json.loads(raw["meta.json"])
    assert meta == {"scene": "0a1b2c3d", "dataset": "src", "frames": list(range(8)), "layout": "scene"}
    assert np.allclose(np.load(io.BytesIO(raw["extrinsics.npy"])), c2w, atol=1e-5)
    np.testing.assert_allclose(np.load(io.BytesIO(raw["intrinsics.npy"]))[frames], intr.numpy(), atol=1e-6)
    offsets = np.load(io.BytesIO(raw["frames.offsets.npy"]))
    assert offsets[0] == 0 and offsets[-1] == len(raw["frames.jpgs"]) and list(raw)[-1] == "frames.jpgs"
    for f in range(8):
        stored = Image.open(io.BytesIO(raw["frames.jpgs"][offsets[f] : offsets[f + 1]]))
        assert np.abs(np.asarray(stored, dtype=np.float64) - expected_crop(entry, f)).mean() < 3.0

    # Training draws its examples from it at run time, every frame a candidate.
    train = DataModule(
        root=str(tmp_path / "out"),
        image_size=SIZE,
        num_workers=0,
        batch_size=4,
        gap_initial=(3, 7),
        gap_final=(3, 7),
        train_batches_per_epoch=25,
        shuffle_buffer=1,
    )
    drawn = [key for b in train.train_dataloader() for key in sample_keys(b)]
    assert {f for _, frames in drawn for f in frames} == set(range(8))
    assert {frames[1] - frames[0] for _, frames in drawn} == {3, 4, 5, 6, 7}
    for b in train.train_dataloader():
        views = torch.cat([b.context.index, b.target.index], 1)
        extr = torch.cat([b.context.extrinsics, b.target.extrinsics], 1)
        reflect = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
        for i in range(b.batch_size):
            plain = s.extrinsics[views[i]]
            assert torch.allclose(extr[i], plain, atol=1e-5) or torch.allclose(
                extr[i], reflect @ plain @ reflect, atol=1e-5
            )


def expected_crop(entry: dict, frame: int) -> np.ndarray:
    """The source frame's centre crop (columns 8..56 of the 64-wide frame) resized to SIZE, by PIL directly."""
    source = Image.open(io.BytesIO(bytes(entry["images"][frame].tolist())))
    return np.array(
        source.crop((8, 0, 56, 48)).resize((SIZE, SIZE), Image.Resampling.BICUBIC), dtype=np.float64
    )


def test_webdataset_reads_the_shards(synthetic_shards):
    import webdataset as wds

    shard = sorted((synthetic_shards / "test").glob("*.tar"))[0]
    sample = next(iter(wds.WebDataset(str(shard), shardshuffle=False)))
    assert {"ctx0.jpg", "ctx1.jpg", "tgt0.jpg", "extrinsics.npy", "intrinsics.npy", "meta.json"} <= set(sample)
    meta = json.loads(sample["meta.json"])
    assert set(meta) == {"scene", "dataset", "context", "target", "gap", "overlap", "extra", "context_views"}
    assert meta["dataset"] == "synthetic" and meta["context_views"]["2"] == meta["context"]
    shard = sorted((synthetic_shards / "train").glob("*.tar"))[0]
    scene = next(iter(wds.WebDataset(str(shard), shardshuffle=False)))
    assert {"frames.jpgs", "frames.offsets.npy", "extrinsics.npy", "intrinsics.npy", "meta.json"} <= set(scene)
    assert len(np.load(io.BytesIO(scene["frames.offsets.npy"]))) == 12 + 1  # 12 frames


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
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=4, progress=False)
    tr, te = manifest["splits"]["train"], manifest["splits"]["test"]
    assert tr["skips"] == {"corrupt_image": 1, "degenerate_baseline": 1, "fov_too_wide": 1, "too_few_frames": 1,
                           "mixed_image_sizes": 1, "shorter_than_min_gap": 1}  # fmt: skip
    assert tr["scenes"] == 1 and tr["scenes_seen"] == 7 and tr["samples"] == 1
    assert set(tr["refused"]) == {"wrongshape", "wide", "static", "corrupt", "short", "brief"}
    assert all(message.startswith(f"{key}:") and "\n" not in message for key, message in tr["refused"].items())
    assert te["skips"] == {"fov_too_wide": 1, "not_in_evaluation_index": 1}
    assert te["samples"] == 1 and te["evaluation_index_missing"] == 1
    for split in ("train", "test"):
        for shard in manifest["splits"][split]["shards"]:
            assert len(shard["sha256"]) == 64

    # The same scenes pass when the limits allow them.
    loose = convert_dataset(tmp_path / "src", tmp_path / "out2", size=16, min_gap=2, max_fov_deg=130,
                            progress=False)  # fmt: skip
    assert "fov_too_wide" not in loose["splits"]["train"]["skips"]
    strict = convert_dataset(tmp_path / "src", tmp_path / "out3", size=16, expect_shape=(H, W + 2),
                             progress=False)  # fmt: skip
    assert strict["splits"]["train"]["samples"] == 0


def test_conversion_resumes_and_verifies(tmp_path, synthetic_src):
    out = tmp_path / "out"
    first = convert_dataset(synthetic_src, out, size=16, workers=2, progress=False)
    shards = sorted((out / "train").glob("*.tar"))
    assert len(shards) >= 2 and verify_shards(out) == []
    stamps = {p.name: p.stat().st_mtime_ns for p in shards}
    shards[1].unlink()  # an interrupted run: one shard never finished
    (out / "train" / (shards[1].stem + ".tar.tmp")).write_bytes(b"partial")
    assert verify_shards(out) == [f"train/{shards[1].name}"]
    again = convert_dataset(synthetic_src, out, size=16, workers=2, progress=False)
    assert again["splits"] == first["splits"]
    assert shards[1].exists() and verify_shards(out) == [] and not list(out.glob("*/*.tmp"))
    for p in shards[:1] + shards[2:]:
        assert p.stat().st_mtime_ns == stamps[p.name]  # finished shards were kept, not rewritten

    data = bytearray(shards[0].read_bytes())  # bit rot: the checksum catches it, a rerun repairs it
    data[600] ^= 0xFF
    shards[0].write_bytes(bytes(data))
    assert verify_shards(out) == [f"train/{shards[0].name}"]
    os.utime(shards[0])
    convert_dataset(synthetic_src, out, size=16, workers=1, progress=False)
    assert verify_shards(out) == []

    # Other options or another evaluation index: a different conversion, never a silent reuse.
    other = convert_dataset(synthetic_src, out, size=20, progress=False)
    assert other["config"]["size"] == 20
    index = json.loads((synthetic_src / "evaluation_index.json").read_text())
    index[sorted(index)[0]] = None
    changed = tmp_path / "index.json"
    changed.write_text(json.dumps(index))
    fewer = convert_dataset(synthetic_src, out, size=20, eval_index=changed, progress=False)
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
               "--workers", "2"]  # fmt: skip
    done = subprocess.run(convert, check=True, capture_output=True, text=True)
    summary = json.loads(done.stdout)
    assert summary["train"]["samples"] == 2 and summary["test"]["samples"] == 1
    assert json.loads((out / "manifest.json").read_text())["config"]["size"] == 14
    to_shards = load_script("to_shards", DATA_PREP)
    for damage, code in ((False, 0), (True, 1)):
        if damage:
            next((out / "test").glob("*.tar")).write_bytes(b"damaged")
        with pytest.raises(SystemExit) as verdict:
            to_shards.main(["--verify", "--out", str(out)])
        assert verdict.value.code == code
    # Options of pre-drawn samples: one line saying what replaced them.
    with pytest.raises(SystemExit) as verdict:
        to_shards.main(["--src", str(src), "--out", str(tmp_path / "o2"), "--samples-per-scene", "8"])
    assert verdict.value.code == 2 and not (tmp_path / "o2").exists()
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
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=2, progress=False)
    assert manifest["splits"]["train"]["skips"] == {"corrupt_chunk": 1}
    assert manifest["splits"]["train"]["samples"] == 1 and manifest["splits"]["test"]["samples"] == 1
    err = capsys.readouterr().err
    assert "to_shards: train/000001.torch: skipped (corrupt_chunk): cannot read chunk" in err
    assert sorted(p.name for p in (tmp_path / "out" / "train").iterdir()) == [
        "train-000000.json",
        "train-000000.tar",
    ]
    assert [s["source"] for s in manifest["splits"]["train"]["shards"]] == ["000000.torch"]
    assert verify_shards(tmp_path / "out") == []


def test_skipped_scenes_are_named_on_stderr(tmp_path, scene, capsys):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    fine = chunk_entry("fine", images, c2w, k)
    broken = chunk_entry("nan_camera", images, c2w, k)
    broken["cameras"][0, 0] = float("nan")
    write_source(tmp_path / "src", [fine, broken], [fine], {"fine": {"context": [0, 4], "target": [1, 2, 3]}})
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=2, progress=False)
    assert manifest["splits"]["train"]["skips"] == {"bad_intrinsics": 1}
    err = capsys.readouterr().err
    assert "to_shards: train/000000.torch: skipped (bad_intrinsics): nan_camera: a focal length" in err
    assert "fine" not in err


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
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=3, specular_threshold=0.2,
                               progress=False)  # fmt: skip

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


# -------------------------------------------------------------------------------------------- careless inputs


def one_line_exit(main, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as verdict:
        main(argv)
    message = str(verdict.value)
    assert verdict.value.code not in (0, None) and message.startswith("to_shards.py: ") and "\n" not in message
    return message


def test_a_changed_source_is_converted_again(tmp_path, scene):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    write_source(tmp_path / "src", [chunk_entry("a", images, c2w, k)], [chunk_entry("a", images, c2w, k)],
                 {"a": {"context": [1, 6], "target": [3]}})  # fmt: skip
    convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=2, progress=False)
    shard = tmp_path / "out" / "train" / "train-000000.tar"
    kept = tmp_path / "out" / "test" / "test-000000.tar"
    stamps = shard.stat().st_mtime_ns, kept.stat().st_mtime_ns
    moved = c2w.copy()
    moved[:, :3, 3] += 1.0  # the same scene re-exported with other poses: the chunk file changes
    torch.save([chunk_entry("a", images, moved, k)], tmp_path / "src" / "train" / "000000.torch")
    convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=2, progress=False)
    assert shard.stat().st_mtime_ns != stamps[0] and kept.stat().st_mtime_ns == stamps[1]
    raw = dict(read_tar(shard))["a"]
    assert np.allclose(np.load(io.BytesIO(raw["extrinsics.npy"])), moved, atol=1e-5)  # not the stale poses


def test_a_full_disk_leaves_no_temporary_file_and_is_one_line(tmp_path, synthetic_src, monkeypatch):
    import errno
    import tarfile

    real = tarfile.TarFile.addfile
    written = []

    def fill_up(self, info, fileobj=None):
        written.append(info.name)
        if len(written) > 12:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, info, fileobj)

    monkeypatch.setattr(tarfile.TarFile, "addfile", fill_up)
    out = tmp_path / "out"
    with pytest.raises(UserError, match="No space left on device; free space") as err:
        convert_dataset(synthetic_src, out, size=16, progress=False)
    assert f"cannot write {out}/" in str(err.value) and ".tar: No space" in str(err.value)
    assert "\n" not in str(err.value)
    assert not list(out.rglob("*.tmp")) and not (out / "manifest.json").exists()
    written.clear()
    to_shards = load_script("to_shards", DATA_PREP).main
    message = one_line_exit(to_shards, ["--src", str(synthetic_src), "--out", str(out), "--size", "16"])
    assert "No space left on device" in message and not list(out.rglob("*.tmp"))
    monkeypatch.setattr(tarfile.TarFile, "addfile", real)  # space again: the same command finishes the job
    convert_dataset(synthetic_src, out, size=16, progress=False)
    assert verify_shards(out) == []


def test_a_target_that_repeats_a_context_frame_converts_and_reads_back(tmp_path, scene):
    """The literature's indices (pixelSplat's, NAS3R's) list some context frames as targets too: such an entry
    converts, and the shared frame reads back the same as context and as target."""
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    entry = chunk_entry(
        "0a1b2c3d", images, s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    )
    evaluation = {"0a1b2c3d": {"context": [1, 6], "target": [1, 4, 6], "overlap": 0.5}}
    write_source(tmp_path / "src", [entry], [entry], evaluation)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=SIZE, min_gap=3, progress=False)
    assert manifest["splits"]["test"]["samples"] == 1
    batch = next(iter(DataModule(root=str(tmp_path / "out"), image_size=SIZE, num_workers=0).eval_dataset()))
    assert batch.context.index.tolist() == [[1, 6]] and batch.target.index.tolist() == [[1, 4, 6]]
    for c, t in ((0, 0), (1, 2)):
        assert torch.equal(batch.context.images[0, c], batch.target.images[0, t])
        assert torch.equal(batch.context.extrinsics[0, c], batch.target.extrinsics[0, t])


def test_damaged_manifest_and_malformed_indices_are_one_line(tmp_path, synthetic_src):
    to_shards = load_script("to_shards", DATA_PREP).main
    out = tmp_path / "out"
    convert_dataset(synthetic_src, out, size=16, progress=False)
    (out / "manifest.json").write_text('{"version": 2, "splits": {"train": ')
    message = one_line_exit(to_shards, ["--verify", "--out", str(out)])
    assert "manifest.json is damaged (not valid JSON" in message and "--src SRC --out" in message
    (out / "manifest.json").write_text('{"version": 2, "splits": {"train": {"shards": [{"sha256": "x"}]}}}')
    assert "lists a shard without a file name" in one_line_exit(to_shards, ["--verify", "--out", str(out)])
    with pytest.raises(UserError, match="no `splits` object"):
        (out / "manifest.json").write_text("[]")
        DataModule(root=str(out), image_size=16).train_dataloader()

    index = json.loads((synthetic_src / "evaluation_index.json").read_text())
    key = sorted(index)[0]
    bad_entries = {
        "negative": ({"context": [-1, 5], "target": [2]}, "negative frame index (-1)"),
        "not a list": ({"context": 3, "target": [2]}, "`context` must be a list of at least 2"),
        "one context": ({"context": [3], "target": [2]}, "`context` must be a list of at least 2"),
        "float": ({"context": [0, 5.5], "target": [2]}, "must hold whole numbers"),
        "twice": ({"context": [0, 5], "target": [2, 2]}, "lists a frame twice"),
        "string": ("0,5", "must be null or an object"),
    }
    for name, (entry, expected) in bad_entries.items():
        path = tmp_path / f"{name.replace(' ', '_')}.json"
        path.write_text(json.dumps({**index, key: entry}))
        message = one_line_exit(to_shards, ["--src", str(synthetic_src), "--out", str(tmp_path / "x"),
                                            "--eval-index", str(path)])  # fmt: skip
        assert f"evaluation index {path}: entry {key!r}" in message and expected in message, (name, message)
    (tmp_path / "broken.json").write_text("{not json")
    assert "is not valid JSON" in one_line_exit(
        to_shards,
        [
            "--src",
            str(synthetic_src),
            "--out",
            str(tmp_path / "x"),
            "--eval-index",
            str(tmp_path / "broken.json"),
        ],
    )
    assert not (tmp_path / "x").exists()  # refused before anything is written


def test_evaluation_samples_carry_k_view_contexts_on_the_same_targets(tmp_path, scene):
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    entry = chunk_entry("room", images, c2w, k)
    write_source(tmp_path / "src", [entry], [entry], {"room": {"context": [0, 7], "target": [2, 5]}})
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=SIZE, min_gap=2, eval_context_views=5,
                               progress=False)  # fmt: skip
    stated = manifest["splits"]["test"]["evaluation_samples"]["room"]
    assert stated["context_views"] == {"2": [0, 7], "3": [0, 3, 7], "4": [0, 3, 4, 7], "5": [0, 1, 3, 6, 7]}
    for views in (2, 3, 4, 5):
        dm = DataModule(
            root=str(tmp_path / "out"), image_size=SIZE, num_workers=0, eval_num_context_views=views
        )
        batch = next(iter(dm.test_dataloader()))
        assert batch.context.index[0].tolist() == stated["context_views"][str(views)]
        assert batch.target.index[0].tolist() == [2, 5]  # the same targets at every count
        got = batch.context.images[0].permute(0, 2, 3, 1).float()
        for v, f in enumerate(batch.context.index[0].tolist()):
            assert torch.allclose(batch.context.extrinsics[0, v], s.extrinsics[f], atol=1e-5)
            assert (got[v] - torch.from_numpy(expected_crop(entry, f)).float()).abs().mean() < 3.0
    with pytest.raises(UserError, match="carry contexts of up to 5 views, not 6: convert again"):
        DataModule(root=str(tmp_path / "out"), image_size=SIZE, eval_num_context_views=6).test_dataloader()


def test_long_scenes_convert_whole_or_strided(tmp_path):
    """A DL3DV-length scene (300 frames) becomes one training sample of 300 frames; --frame-stride 3 keeps
    every third frame, and the stream draws from the kept ones."""
    frames = 300
    tile = (np.random.default_rng(0).random((H, W, 3)) * 255).astype(np.uint8)
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    c2w[:, 0, 3] = np.linspace(0.0, 3.0, frames)  # a walk along x
    k = np.tile(np.array([[0.9, 0, 0.5], [0, 1.2, 0.5], [0, 0, 1]]), (frames, 1, 1))
    entry = chunk_entry("long", np.repeat(tile[None], frames, 0), c2w, k)
    write_source(tmp_path / "src", [entry], [entry], {"long": {"context": [100, 160], "target": [130]}})
    whole = convert_dataset(tmp_path / "src", tmp_path / "whole", size=8, min_gap=25, progress=False)
    assert whole["splits"]["train"]["frames"] == frames
    strided = convert_dataset(tmp_path / "src", tmp_path / "strided", size=8, min_gap=25, frame_stride=3,
                              progress=False)  # fmt: skip
    assert strided["splits"]["train"]["shards"][0]["scene_frames"] == {"long": 100}
    meta = json.loads(dict(read_tar(tmp_path / "strided" / "train" / "train-000000.tar"))["long"]["meta.json"])
    assert meta["frames"] == list(range(0, frames, 3))
    dm = DataModule(
        root=str(tmp_path / "strided"),
        image_size=8,
        num_workers=0,
        batch_size=2,
        gap_initial=(25, 45),
        gap_final=(25, 45),
        train_batches_per_epoch=4,
        flip_augment=False,
    )
    for b in dm.train_dataloader():
        assert torch.all(b.context.index % 3 == 0) and torch.all((b.gap >= 25) & (b.gap <= 45))
        assert torch.equal(b.context.index[:, 1] - b.context.index[:, 0], 3 * b.gap)  # gaps count kept frames
        assert torch.allclose(b.context.extrinsics[:, :, 0, 3], b.context.index.float() * 3.0 / (frames - 1))


def test_scene_keys_of_any_characters_survive_conversion_or_are_refused_by_name(tmp_path, scene, capsys):
    """Distinct keys keep their exact text in every sample (evaluation results and the manifest name scenes
    by it); two scenes whose shard keys would be one, or one key given twice, are refused in one line each."""
    s, r = scene
    images = (r.images * 255).round().to(torch.uint8).numpy()
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().expand(8, 3, 3).numpy()
    keys = [*ODD_KEYS, "room.one", "room_one", "CASE"]  # the last three: shard keys taken, a key given twice
    scenes = [chunk_entry(key, images, c2w, k) for key in keys]
    evaluation = {key: {"context": [1, 6], "target": [2, 3, 5]} for key in keys}
    write_source(tmp_path / "src", scenes[:1], scenes, evaluation)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, min_gap=3, progress=False)

    test = manifest["splits"]["test"]
    assert test["skips"] == {"duplicate_key": 3}
    assert set(test["evaluation_samples"]) == set(ODD_KEYS)
    samples = list(read_tar(next((tmp_path / "out" / "test").glob("*.tar"))))
    assert sorted(json.loads(raw["meta.json"])["scene"] for _, raw in samples) == sorted(ODD_KEYS)
    assert len({key for key, _ in samples}) == len(ODD_KEYS)
    err = capsys.readouterr().err
    assert "skipped (duplicate_key): 'room.one': its shard key 'room_one' is taken by 'room one'" in err
    assert "skipped (duplicate_key): 'CASE': its shard key 'CASE' is taken by 'CASE'" in err

    twice = tmp_path / "src2"  # one key in two source files of a split: the conversion stops, naming both
    write_source(twice, scenes[:1], scenes[:1], {})
    torch.save(scenes[:1], twice / "train" / "000001.torch")
    (twice / "train" / "index.json").unlink()  # without an index every chunk of the folder is read
    with pytest.raises(UserError, match=r"scene key 'room one' is in two source files of the train split "
                       r"\(000000.torch and 000001.torch\)"):  # fmt: skip
        convert_dataset(twice, tmp_path / "out2", size=16, min_gap=3, progress=False)
