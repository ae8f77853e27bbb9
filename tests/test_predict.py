"""`aesplat predict`: image loading, camera paths, checkpoint loading and the files it writes."""

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.camera_path import interpolate_cameras, slerp
from aesplat.checkpoint import load_checkpoint
from aesplat.errors import UserError
from aesplat.geometry import make_pose, matrix_to_quat, quat_to_matrix
from aesplat.images import colorize_depth, load_image, model_image_shape
from aesplat.predict import main
from tests.helpers import IMAGE_SIZE, SH_DEGREE, tree, write_tiny_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("run"))


def save_png(path: Path, array: np.ndarray) -> Path:
    Image.fromarray(array.astype(np.uint8)).save(path)
    return path


# ----------------------------------------------------------------------------------------------- images


def _thirds(height: int, width: int) -> np.ndarray:
    """Left, middle and right thirds red, green, blue."""
    img = np.zeros((height, width, 3), np.uint8)
    third = width // 3
    img[:, :third, 0] = img[:, third : 2 * third, 1] = img[:, 2 * third :, 2] = 255
    return img


def test_load_image_keeps_the_aspect_ratio_with_the_short_side_at_size(tmp_path):
    out = load_image(save_png(tmp_path / "wide.png", _thirds(30, 90)), 14)
    assert out.image.shape == (3, 14, 42) and out.image.dtype == torch.float32  # 3:1, a 1 x 3 token grid
    assert out.source == (90, 30) and out.crop == (0.0, 0.0, 90.0, 30.0) and not out.cropped
    for third, channel in enumerate((0, 1, 2)):  # the whole photo: all three colours, in place
        assert out.image[channel, :, 14 * third + 2 : 14 * third + 12].min() > 0.95
    # 16:9 with 14-pixel patches at 28: 49.8 px rounds to 56 (4 patches); the 1-pixel sliver is cropped
    assert load_image(save_png(tmp_path / "hd.png", np.zeros((90, 160, 3))), 28).image.shape == (3, 28, 56)
    assert model_image_shape(160, 90, 28, 14) == (28, 56) and model_image_shape(90, 160, 28, 7) == (49, 28)


def test_load_image_crops_a_centre_square_when_asked_and_says_so(tmp_path):
    out = load_image(save_png(tmp_path / "wide.png", _thirds(30, 90)), 14, crop="square")
    assert out.image.shape == (3, 14, 14)
    centre = out.image[:, :, 2:-2]
    assert centre[1].min() > 0.95 and centre[0].max() < 0.05 and centre[2].max() < 0.05
    assert out.cropped and out.crop == (30.0, 0.0, 60.0, 30.0)
    assert out.crop_record() == {"width": 90, "height": 30, "crop": [30.0, 0.0, 60.0, 30.0], "cropped": True}
    # another photo of the scene at another aspect ratio is centre-cropped to the first one's shape
    tall = load_image(save_png(tmp_path / "tall.png", np.zeros((60, 30, 3))), 14, shape=(14, 42))
    assert tall.image.shape == (3, 14, 42) and tall.cropped and tall.crop == (0.0, 25.0, 30.0, 35.0)


def test_load_image_errors_name_the_file(tmp_path):
    bad = tmp_path / "notes.png"
    bad.write_text("not an image")
    with pytest.raises(ValueError, match="notes.png"):
        load_image(bad, 28)
    with pytest.raises(ValueError, match="does not exist"):
        load_image(tmp_path / "missing.jpg", 28)


def test_colorize_depth_maps_near_and_far_to_the_ends_of_the_colour_map():
    from matplotlib import colormaps

    depth = torch.linspace(1.0, 10.0, 100).reshape(10, 10)
    depth[0, 0] = 0.0  # nothing seen
    rgb = colorize_depth(depth)
    assert rgb.shape == (10, 10, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 0] == 0).all()
    turbo = colormaps["turbo"]
    np.testing.assert_allclose(rgb[-1, -1], np.round(np.array(turbo(0.0)[:3]) * 255), atol=1)  # far
    np.testing.assert_allclose(rgb[0, 2], np.round(np.array(turbo(1.0)[:3]) * 255), atol=1)  # near


# ----------------------------------------------------------------------------------------------- cameras


def rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_slerp_halfway_is_half_the_angle():
    q0 = matrix_to_quat(torch.eye(3))[None]
    q1 = matrix_to_quat(rot_z(math.pi / 2))[None]
    mid = quat_to_matrix(slerp(q0, q1, torch.tensor([0.5])))[0]
    torch.testing.assert_close(mid, rot_z(math.pi / 4), atol=1e-6, rtol=0)
    same = slerp(q0, q0, torch.tensor([0.3]))  # equal rotations: no 0 / 0
    torch.testing.assert_close(same, q0)


def test_interpolate_cameras_passes_through_every_camera():
    ext = torch.stack([make_pose(rot_z(a), torch.tensor([a, 0.0, 0.5 * a])) for a in (0.0, 0.4, 1.0)])
    intr = torch.eye(3).repeat(3, 1, 1)
    intr[:, 0, 0] = torch.tensor([1.0, 1.2, 0.8])
    path_ext, path_int = interpolate_cameras(ext, intr, 5)  # frames at 0, 0.5, 1, 1.5, 2
    assert path_ext.shape == (5, 4, 4) and path_int.shape == (5, 3, 3)
    torch.testing.assert_close(path_ext[[0, 2, 4]], ext, atol=1e-6, rtol=0)
    torch.testing.assert_close(path_int[[0, 2, 4]], intr)
    torch.testing.assert_close(path_ext[1, :3, :3], rot_z(0.2), atol=1e-6, rtol=0)
    torch.testing.assert_close(path_ext[3, :3, 3], torch.tensor([0.7, 0.0, 0.35]))
    assert path_int[3, 0, 0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="two cameras"):
        interpolate_cameras(ext[:1], intr[:1], 5)


# ----------------------------------------------------------------------------------------------- checkpoints


def test_load_checkpoint_restores_the_trained_weights(tiny_ckpt):
    loaded = load_checkpoint(tiny_ckpt)
    assert loaded.sh_degree == SH_DEGREE and loaded.image_size == IMAGE_SIZE and loaded.cameras == "predicted"
    assert not loaded.model.training
    state = torch.load(tiny_ckpt, weights_only=True)["state_dict"]
    for name, value in loaded.model.state_dict().items():
        torch.testing.assert_close(value, state[f"model.{name}"], rtol=0, atol=0)


def test_load_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ckpt does not exist"):
        load_checkpoint(tmp_path / "nope.ckpt")
    torch.save({"something": 1}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="not a Lightning checkpoint"):
        load_checkpoint(tmp_path / "other.ckpt")
    (tmp_path / "text.ckpt").write_text("hello")
    with pytest.raises(ValueError, match="text.ckpt is not a torch file"):
        load_checkpoint(tmp_path / "text.ckpt")
    with pytest.raises(SystemExit, match="aesplat predict: .*not a Lightning checkpoint"):
        main(["--ckpt", str(tmp_path / "other.ckpt"), "--out", str(tmp_path / "out"), "a.png", "b.png"])
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------- end to end


def read_png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(np.float64)


def test_predict_writes_every_output(tiny_ckpt, tmp_path):
    rng = np.random.default_rng(0)
    a = save_png(tmp_path / "a.png", rng.integers(0, 255, (45, 30, 3)))  # 2:3 portrait -> 28 x 42
    b = save_png(tmp_path / "b view.jpg", rng.integers(0, 255, (36, 50, 3)))  # landscape: cropped to 2:3
    out = tmp_path / "out"
    assert main(["--ckpt", str(tiny_ckpt), "--out", str(out), "--novel-frames", "3", "--no-progress",
                 str(a), str(b)]) == 0  # fmt: skip
    h, w = 42, IMAGE_SIZE

    header = (out / "gaussians.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert f"element vertex {2 * h * w}" in header
    assert header.count("property float f_rest_") == 3 * ((SH_DEGREE + 1) ** 2 - 1)

    cams = json.loads((out / "cameras.json").read_text())
    assert [v["image"] for v in cams["views"]] == ["a", "b view"] and len(cams["novel"]) == 3
    view0, view1 = cams["views"]
    np.testing.assert_allclose(view0["camera_to_world"], np.eye(4), atol=1e-6)  # the canonical frame
    k_norm, k_pix = np.array(view1["intrinsics_normalized"]), np.array(view1["intrinsics_pixels"])
    np.testing.assert_allclose(k_pix[0], k_norm[0] * w, rtol=1e-6)
    np.testing.assert_allclose(k_pix[1], k_norm[1] * h, rtol=1e-6)
    assert k_pix[0, 0] == pytest.approx(k_pix[1, 1], rel=1e-5)  # square pixels
    c2w, w2c = np.array(view1["camera_to_world"]), np.array(view1["world_to_camera"])
    np.testing.assert_allclose(c2w @ w2c, np.eye(4), atol=1e-5)
    assert (view1["width"], view1["height"]) == (w, h)
    assert view0["source"] == {"width": 30, "height": 45, "crop": [0.0, 0.0, 30.0, 45.0], "cropped": False}
    assert view1["source"]["cropped"] and view1["source"]["crop"] == [13.0, 0.0, 37.0, 36.0]  # 24 x 36: 2:3

    for folder in ("inputs", "renders", "depth"):
        pngs = sorted((out / folder).glob("*.png"))
        assert [p.name for p in pngs] == ["00_a.png", "01_b view.png"]
        assert Image.open(pngs[0]).size == (w, h)
    depth = np.load(out / "depth" / "00_a.npy")
    assert depth.shape == (h, w) and ((depth >= 0.1 - 1e-4) & (depth <= 20.0 + 1e-4)).all()
    assert sorted(p.name for p in (out / "novel").iterdir()) == [
        "000.png",
        "001.png",
        "002.png",
        "trajectory.gif",
    ]
    assert Image.open(out / "novel" / "001.png").size == (w, h)
    # The path starts at the first input camera and ends at the last: its end frames are the re-renders.
    assert np.abs(read_png(out / "novel" / "000.png") - read_png(out / "renders" / "00_a.png")).mean() < 1.0
    assert (
        np.abs(read_png(out / "novel" / "002.png") - read_png(out / "renders" / "01_b view.png")).mean() < 1.0
    )


def test_a_2_to_1_photo_pair_gives_2_to_1_gaussians_renders_and_cameras(tiny_ckpt, tmp_path, capsys):
    rng = np.random.default_rng(2)
    photos = [str(save_png(tmp_path / f"wide{i}.png", rng.integers(0, 255, (60, 120, 3)))) for i in range(2)]
    out = tmp_path / "out"
    assert main(["--ckpt", str(tiny_ckpt), "--out", str(out), "--novel-frames", "2", "--no-progress",
                 *photos]) == 0  # fmt: skip
    h, w = IMAGE_SIZE, 2 * IMAGE_SIZE
    header = (out / "gaussians.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert f"element vertex {2 * h * w}" in header
    for folder in ("inputs", "renders", "depth", "novel"):
        assert {Image.open(p).size for p in (out / folder).glob("*.png")} == {(w, h)}, folder
    assert np.load(out / "depth" / "01_wide1.npy").shape == (h, w)
    cams = json.loads((out / "cameras.json").read_text())
    for view in [*cams["views"], *cams["novel"]]:
        k = np.array(view["intrinsics_normalized"])
        assert k[0, 0] / k[1, 1] == pytest.approx(0.5, rel=1e-5)  # fx / fy = H / W: square pixels
        assert view["fov_x_deg"] > view["fov_y_deg"]
    assert not any(v["source"]["cropped"] for v in cams["views"])
    assert "2 views of 56x28 pixels" in capsys.readouterr().out


def test_predict_with_three_images_writes_three_views(tmp_path):
    ckpt = write_tiny_checkpoint(tmp_path / "pool", view_aggregation="pool")
    state = torch.load(ckpt, weights_only=False)  # a new camera head puts every view at view 0's pose: move it
    pose = "model.camera_head.pose_branch.fc2.weight"
    shape = state["state_dict"][pose].shape
    state["state_dict"][pose] = torch.randn(shape, generator=torch.Generator().manual_seed(0))
    torch.save(state, ckpt)
    rng = np.random.default_rng(4)
    images = [str(save_png(tmp_path / f"{i}.png", rng.integers(0, 255, (28, 28, 3)))) for i in range(3)]
    out = tmp_path / "out"
    assert main(["--ckpt", str(ckpt), "--out", str(out), "--novel-frames", "4", "--no-progress", *images]) == 0
    header = (out / "gaussians.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert f"element vertex {3 * IMAGE_SIZE * IMAGE_SIZE}" in header
    cams = json.loads((out / "cameras.json").read_text())
    assert [v["image"] for v in cams["views"]] == ["0", "1", "2"]
    np.testing.assert_allclose(cams["views"][0]["camera_to_world"], np.eye(4), atol=1e-6)
    assert not np.allclose(cams["views"][2]["camera_to_world"], np.eye(4), atol=1e-7)
    for folder in ("inputs", "renders", "depth"):
        assert sorted(p.name for p in (out / folder).glob("*.png")) == ["00_0.png", "01_1.png", "02_2.png"]


def test_the_patch_size_comes_from_the_model(tmp_path):
    """A model with 7-pixel patches trained at 21 px: 21 is no multiple of DINOv2's 14, yet right here."""
    ckpt = write_tiny_checkpoint(tmp_path / "p7", image_size=21, options={"patch_size": 7})
    assert load_checkpoint(ckpt).patch_size == 7
    images = [str(save_png(tmp_path / f"{i}.png", np.full((30, 40, 3), 40 * i + 50))) for i in range(2)]
    out = tmp_path / "out"
    assert main(["--ckpt", str(ckpt), "--out", str(out), "--novel-frames", "2", "--no-progress", *images]) == 0
    assert Image.open(out / "renders" / "00_0.png").size == (28, 21)  # 4:3 -> 4 x 3 patches of 7
    with pytest.raises(SystemExit, match="--size 16 is not a multiple of the model's patch size 7"):
        main(["--ckpt", str(ckpt), "--out", str(tmp_path / "o2"), "--size", "16", *images])


def test_predict_on_cpu_renders_with_torch_on_a_gsplat_machine(tiny_ckpt, tmp_path, pretend_gsplat):
    """`--device cpu` on a GPU node: the default backend "auto" follows the CPU tensors to the torch backend."""
    images = [save_png(tmp_path / f"{i}.png", np.full((28, 28, 3), 60 * i + 40)) for i in range(2)]
    args = ["--ckpt", str(tiny_ckpt), "--out", str(tmp_path / "out"), "--novel-frames", "2", "--no-progress"]
    assert main([*args, "--device", "cpu", *map(str, images)]) == 0
    assert (tmp_path / "out" / "renders" / "01_1.png").is_file()


def test_predict_rejects_bad_input(tiny_ckpt, tmp_path):
    good = save_png(tmp_path / "good.png", np.zeros((28, 28, 3)))
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"\xff\xd8 truncated")
    out = str(tmp_path / "out")
    with pytest.raises(SystemExit, match="broken.jpg"):
        main(["--ckpt", str(tiny_ckpt), "--out", out, str(good), str(bad)])
    with pytest.raises(SystemExit, match="at least two images"):
        main(["--ckpt", str(tiny_ckpt), "--out", out, str(good)])
    with pytest.raises(SystemExit, match="not a multiple of the model's patch size 14"):
        main(["--ckpt", str(tiny_ckpt), "--out", out, "--size", "30", str(good), str(good)])
    # the refusal names what predict can do (two photos, or another checkpoint), not a training setting
    with pytest.raises(SystemExit, match=r"takes 2 photos; got 3\. Give 2, or a checkpoint trained .*pool"):
        main(["--ckpt", str(tiny_ckpt), "--out", out, str(good), str(good), str(good)])
    with pytest.raises(SystemExit, match="ply-sh-degree"):
        main(["--ckpt", str(tiny_ckpt), "--out", out, "--ply-sh-degree", "4", str(good), str(good)])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_predict_on_cuda_matches_the_cpu(tiny_ckpt, tmp_path):
    """`aesplat predict --device cuda` (rendering with gsplat when it is installed) against `--device cpu`."""
    rng = np.random.default_rng(3)
    images = [str(save_png(tmp_path / f"{i}.png", rng.integers(0, 255, (40, 40, 3)))) for i in range(2)]
    for device in ("cpu", "cuda"):
        args = [
            "--ckpt",
            str(tiny_ckpt),
            "--out",
            str(tmp_path / device),
            "--novel-frames",
            "2",
            "--no-progress",
        ]
        assert main([*args, "--no-progress", "--device", device, *images]) == 0
    cpu, cuda = (json.loads((tmp_path / d / "cameras.json").read_text()) for d in ("cpu", "cuda"))
    for a, b in zip(cpu["views"], cuda["views"]):
        # Loose: cuDNN convolutions may run in TF32; a wrong device path would be far off.
        np.testing.assert_allclose(a["camera_to_world"], b["camera_to_world"], atol=2e-2)
        np.testing.assert_allclose(a["intrinsics_normalized"], b["intrinsics_normalized"], atol=2e-2)
    for name in ("00_0", "01_1"):
        depth_cpu, depth_cuda = (np.load(tmp_path / d / "depth" / f"{name}.npy") for d in ("cpu", "cuda"))
        assert np.isfinite(depth_cuda).all()
        np.testing.assert_allclose(depth_cuda, depth_cpu, rtol=2e-2)
        # gsplat caps alpha at 0.999 where the torch backend uses 0.99: the images agree to a few levels.
        diff = np.abs(read_png(tmp_path / "cuda" / "renders" / f"{name}.png") - read_png(
            tmp_path / "cpu" / "renders" / f"{name}.png"))  # fmt: skip
        assert diff.mean() < 3.0, diff.mean()
    header = (tmp_path / "cuda" / "gaussians.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert f"element vertex {2 * IMAGE_SIZE * IMAGE_SIZE}" in header


def test_predict_refuses_a_checkpoint_trained_with_the_data_sets_cameras(tmp_path):
    ckpt = write_tiny_checkpoint(tmp_path / "posed", cameras="dataset")
    assert load_checkpoint(ckpt).cameras == "dataset"
    good = save_png(tmp_path / "good.png", np.zeros((28, 28, 3)))
    with pytest.raises(SystemExit, match="trained with model.cameras=dataset"):
        main(["--ckpt", str(ckpt), "--out", str(tmp_path / "out"), str(good), str(good)])
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------- input rules


def test_16_bit_images_keep_their_range(tmp_path):
    ramp = np.tile(np.linspace(0, 65535, 28).round().astype(np.uint16), (28, 1))  # left black, right white
    path = tmp_path / "grey16.png"
    Image.fromarray(ramp).save(path)
    assert Image.open(path).mode.startswith("I")
    out = load_image(path, 28).image
    np.testing.assert_allclose(out[0].numpy(), ramp / 65535.0, atol=2e-3)  # scaled, not clipped at 255
    assert (out[0] > 0.99).float().mean() < 0.1  # (clipping turned 91 % of such a picture white)
    assert torch.equal(out[0], out[1]) and torch.equal(out[1], out[2])
    # a large 16-bit photo, shrunk before it becomes floats, keeps its range too
    big = np.tile(np.linspace(0, 65535, 280).round().astype(np.uint16), (280, 1))
    Image.fromarray(big).save(tmp_path / "big16.png")
    out = load_image(tmp_path / "big16.png", 28).image
    np.testing.assert_allclose(out[0].numpy(), ramp / 65535.0, atol=2e-2)


def test_transparent_pixels_are_composited_over_the_background(tmp_path):
    rgba = np.zeros((28, 28, 4), np.uint8)
    rgba[..., 0] = 255  # red, opaque on the left half, transparent on the right
    rgba[:, :14, 3] = 255
    path = tmp_path / "cutout.png"
    Image.fromarray(rgba, mode="RGBA").save(path)
    out = load_image(path, 28, background=(0.0, 0.0, 1.0)).image
    assert out[0, :, :12].min() > 0.99 and out[2, :, :12].max() < 0.01  # opaque: its own colour
    assert out[0, :, 16:].max() < 0.01 and out[2, :, 16:].min() > 0.99  # transparent: the background


def test_exif_orientation_is_applied(tmp_path):
    # Stored 40 wide x 20 high, top half white; EXIF 6 says "rotate 90 degrees clockwise to view": upright it
    # is 20 x 40 with the white half on the right.
    stored = np.zeros((20, 40, 3), np.uint8)
    stored[:10] = 255
    exif = Image.Exif()
    exif[0x0112] = 6
    path = tmp_path / "phone.jpg"
    Image.fromarray(stored).save(path, exif=exif, quality=100)
    out = load_image(path, 14)
    assert out.source == (20, 40) and out.image.shape == (3, 28, 14)  # upright: portrait
    assert out.image[:, :, 9:].mean() > 0.9 and out.image[:, :, :5].mean() < 0.1
    square = load_image(path, 14, crop="square").image
    assert square[:, :, 10:].mean() > 0.9 and square[:, :, :4].mean() < 0.1
    # stored 4 times larger, it is decoded reduced, turned the same way
    Image.fromarray(np.kron(stored, np.ones((8, 8, 1), np.uint8))).save(path, exif=exif, quality=100)
    out = load_image(path, 14)
    assert (
        out.image.shape == (3, 28, 14) and out.image[:, :, 9:].mean() > 0.9 and out.image[:, :, :5].mean() < 0.1
    )


def test_images_too_small_for_the_model_are_refused_with_the_minimum(tmp_path):
    tiny = save_png(tmp_path / "dot.png", np.zeros((1, 1, 3)))
    expected = r"is 1x1 pixels, too small for this model's 28x28 input \(images are upscaled by at most 2x\)"
    with pytest.raises(UserError, match=expected + ": give one of at least 14x14 pixels"):
        load_image(tiny, 28)
    assert load_image(save_png(tmp_path / "half.png", np.zeros((14, 21, 3))), 28).image.shape == (3, 28, 42)
    with pytest.raises(UserError, match="at least 21x14 pixels"):
        load_image(save_png(tmp_path / "narrow.png", np.zeros((14, 20, 3))), 28, shape=(28, 42))


def test_a_huge_photo_is_never_decoded_to_floats_at_full_size(tmp_path, monkeypatch):
    from aesplat import images

    seen = []
    to_float = images._to_rgb_float
    monkeypatch.setattr(images, "_to_rgb_float", lambda img, *a: seen.append(img.size) or to_float(img, *a))
    rng = np.random.default_rng(1)
    photo = np.kron(rng.integers(0, 255, (6, 12, 3)), np.ones((200, 200, 1))).astype(np.uint8)  # 2400 x 1200
    for name in ("huge.jpg", "huge.png"):
        Image.fromarray(photo).save(tmp_path / name)
        out = load_image(tmp_path / name, 28)
        assert out.image.shape == (3, 28, 56) and not out.cropped
        w, h = seen.pop()
        assert 112 <= w <= 224 and 56 <= h <= 112, (name, w, h)  # 2 to 4 times the model image, not 2400x1200
        pixels = torch.from_numpy(photo).permute(2, 0, 1)[None].float() / 255
        reference = torch.nn.functional.interpolate(pixels, size=(28, 56), mode="area")[0]
        assert (out.image - reference).abs().mean() < 0.02  # the same picture


def test_a_decompression_bomb_is_refused_in_one_line(tiny_ckpt, tmp_path, monkeypatch):
    bomb = save_png(tmp_path / "bomb.png", np.zeros((100, 100, 3)))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # Pillow refuses more than twice this many pixels
    with pytest.raises(UserError, match="bomb.png' is refused as a possible decompression bomb") as err:
        load_image(bomb, 28)
    assert "\n" not in str(err.value)
    with pytest.raises(SystemExit, match="aesplat predict: .*decompression bomb"):
        main(["--ckpt", str(tiny_ckpt), "--out", str(tmp_path / "out"), str(bomb), str(bomb)])
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------- output folder


def test_a_non_empty_output_folder_is_refused_before_the_model_loads(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "gaussians.ply").write_text("an earlier prediction")
    images = [str(save_png(tmp_path / f"{i}.png", np.zeros((28, 28, 3)))) for i in range(2)]
    # The checkpoint does not exist: the refusal comes first, before anything is loaded.
    with pytest.raises(SystemExit) as info:
        main(["--ckpt", str(tmp_path / "none.ckpt"), "--out", str(out), *images])
    assert str(info.value) == (
        f"aesplat predict: --out {out} is not empty; give a new folder, or --overwrite to replace it "
        "(as a whole)"
    )
    assert tree(out) == {"gaussians.ply": b"an earlier prediction"}
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit, match="is a file, not a folder"):
        main(["--ckpt", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "file"), *images])


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_an_unwritable_output_place_is_refused_before_the_model_loads(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    images = [str(save_png(tmp_path / f"{i}.png", np.zeros((28, 28, 3)))) for i in range(2)]
    with pytest.raises(SystemExit, match=f"cannot write in {locked}"):
        main(["--ckpt", str(tmp_path / "none.ckpt"), "--out", str(locked / "out"), *images])


def test_overwrite_replaces_the_folder_whole_and_a_failure_leaves_it_untouched(
    tiny_ckpt, tmp_path, monkeypatch
):
    from aesplat import predict

    out = tmp_path / "out"
    (out / "novel").mkdir(parents=True)
    (out / "novel" / "099.png").write_text("a frame of an older, longer run")
    (out / "cameras.json").write_text("{}")
    images = [str(save_png(tmp_path / f"{i}.png", np.full((28, 28, 3), 50 * i + 30))) for i in range(2)]
    args = ["--ckpt", str(tiny_ckpt), "--out", str(out), "--novel-frames", "2", "--no-progress", "--overwrite"]
    before = tree(out)

    def broken_ply(*_a, **_k):
        raise OSError("disk full")

    monkeypatch.setattr(predict, "write_ply", broken_ply)  # fails after the renders are written
    with pytest.raises(SystemExit, match="aesplat predict: disk full"):  # one line, as every OSError
        main([*args, *images])
    assert tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["0.png", "1.png", "out"]
    monkeypatch.undo()

    assert main([*args, *images]) == 0
    files = tree(out)
    assert "novel/099.png" not in files and json.loads(files["cameras.json"])["views"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0.png", "1.png", "out"]  # no partial folder left


def test_a_refused_prediction_creates_nothing(tiny_ckpt, tmp_path):
    good = str(save_png(tmp_path / "good.png", np.zeros((28, 28, 3))))
    with pytest.raises(SystemExit, match="takes 2 photos; got 3"):
        main(["--ckpt", str(tiny_ckpt), "--out", str(tmp_path / "out"), good, good, good])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.png"]
