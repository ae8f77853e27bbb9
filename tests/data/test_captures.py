"""Posed captures (nerfstudio, COLMAP text and binary) -> shards: the same cameras and images as the chunk path,
undistortion, refusals, resumption, and `aesplat test` on the result.

The exporters here write the formats from their documentation, independently of the readers: nerfstudio's
camera-to-world in OpenGL axes (y and z columns negated) under an ``applied_transform``, COLMAP's
world-to-camera quaternion and translation, its binary layout packed field by field with ``struct``.
"""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.data import convert_dataset
from aesplat.data.lens import Camera, distorted_pixels, undistort, undistortion_zoom
from aesplat.data.sampler import evaluation_sample
from aesplat.data.sources.colmap import colmap_camera, read_colmap, read_colmap_cameras
from aesplat.data.synthetic_scenes import render_scene, sample_scene, scene_to_chunk_entry
from aesplat.data.tar_files import read_tar
from tests.helpers import REPO

from ..script_loader import DATA_PREP, load_script

H, W = 48, 64
FRAMES = 8
SIZE = 32
INDEX = {"context": [1, 6], "target": [2, 3, 5], "overlap": None}
MODEL_IDS = {
    "SIMPLE_PINHOLE": 0,
    "PINHOLE": 1,
    "SIMPLE_RADIAL": 2,
    "RADIAL": 3,
    "OPENCV": 4,
    "OPENCV_FISHEYE": 5,
}


# -------------------------------------------------------------------------------------------------- exporters


def rotation_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] -> unit quaternion (w, x, y, z), w >= 0 (the largest-component method)."""
    m = r
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q * np.sign(q[0] or 1.0)


def write_images(folder: Path, images: list[bytes], ext: str) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, data in enumerate(images):
        name = f"frame_{i:05d}.{ext}"
        if ext == "png":
            Image.open(io.BytesIO(data)).save(folder / name)
        else:
            (folder / name).write_bytes(data)
        names.append(name)
    return names


def export_nerfstudio(scene_dir: Path, images: list[bytes], c2w: np.ndarray, k: np.ndarray, *,
                      applied: np.ndarray | None = None, per_frame: bool = False, model: str = "PINHOLE",
                      distortion: dict | None = None, folder: str = "images",
                      ext: str = "png") -> Path:  # fmt: skip
    """transforms.json: camera-to-world in OpenGL axes, frames listed in reverse order."""
    names = write_images(scene_dir / folder, images, ext)
    with Image.open(scene_dir / folder / names[0]) as im:
        w, h = im.size
    intr = {"fl_x": k[0, 0] * w, "fl_y": k[1, 1] * h, "cx": k[0, 2] * w, "cy": k[1, 2] * h, "w": w, "h": h}
    intr.update(distortion or {})
    frames = []
    for i in reversed(range(len(names))):
        gl = c2w[i].copy()
        gl[:3, 1:3] *= -1.0  # OpenCV camera axes -> OpenGL (y up, z backward)
        if applied is not None:
            gl = applied @ gl
        frame = {"file_path": f"{folder}/{names[i]}", "transform_matrix": gl.tolist()}
        if per_frame:
            frame.update(intr)
        frames.append(frame)
    meta = {"camera_model": model, "frames": frames}
    if not per_frame:
        meta.update(intr)
    if applied is not None:
        meta["applied_transform"] = applied[:3].tolist()
    scene_dir.mkdir(parents=True, exist_ok=True)
    (scene_dir / "transforms.json").write_text(json.dumps(meta))
    return scene_dir / "transforms.json"


def export_colmap(scene_dir: Path, images: list[bytes], c2w: np.ndarray, k: np.ndarray, *, binary: bool,
                  model: str = "PINHOLE", extra: tuple[float, ...] = (), ext: str = "jpg",
                  points: str = "alternate") -> None:  # fmt: skip
    """sparse/0/{cameras,images}.{txt,bin}: world-to-camera quaternion + translation, one camera. Text models:
    ``points`` ``alternate`` writes every other POINTS2D line empty, ``none`` writes no POINTS2D lines (header
    lines only), ``blank`` adds a stray blank line after every image's two lines."""
    names = write_images(scene_dir / "images", images, ext)
    fx, fy, cx, cy = k[0, 0] * W, k[1, 1] * H, k[0, 2] * W, k[1, 2] * H
    params = [fx, cx, cy] if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else [fx, fy, cx, cy]
    params += list(extra)
    poses = []
    for i in range(len(names)):
        w2c = np.linalg.inv(c2w[i])
        poses.append((i + 10, rotation_to_quaternion(w2c[:3, :3]), w2c[:3, 3], names[i]))
    model_dir = scene_dir / "sparse" / "0"
    model_dir.mkdir(parents=True)
    if binary:
        cams = struct.pack("<Q", 1) + struct.pack("<iiQQ", 7, MODEL_IDS[model], W, H)
        cams += struct.pack(f"<{len(params)}d", *params)
        (model_dir / "cameras.bin").write_bytes(cams)
        data = struct.pack("<Q", len(poses))
        for iid, q, t, name in reversed(poses):
            data += (
                struct.pack("<i", iid) + struct.pack("<4d", *q) + struct.pack("<3d", *t) + struct.pack("<i", 7)
            )
            data += name.encode() + b"\0" + struct.pack("<Q", 2)
            data += struct.pack("<ddq", 1.5, 2.5, -1) + struct.pack("<ddq", 3.5, 4.5, 12)  # two 2D points
        (model_dir / "images.bin").write_bytes(data)
    else:
        (model_dir / "cameras.txt").write_text(
            "# Camera list with one line of data per camera:\n"
            f"7 {model} {W} {H} {' '.join(repr(float(v)) for v in params)}\n"
        )
        lines = [
            "# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, ...",
        ]
        for n, (iid, q, t, name) in enumerate(poses):
            lines.append(f"{iid} {' '.join(repr(float(v)) for v in [*q, *t])} 7 {name}")
            if points != "none":
                lines.append("" if n % 2 else "1.5 2.5 -1 3.5 4.5 12")  # empty points lines are allowed
            if points == "blank":
                lines.append("")
        (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    (model_dir / "points3D.txt").write_text("# not read\n")


# --------------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def scene():
    s = sample_scene(31, frames=FRAMES, height=H, width=W, effects=("textures",), key="room")
    return s, render_scene(s, H, W)


@pytest.fixture(scope="module")
def chunk_reference(scene, tmp_path_factory):
    """The scene through the chunk path: {ext: bytes} of its one test sample, and its JPEG frames."""
    s, r = scene
    root = tmp_path_factory.mktemp("chunk")
    entry = scene_to_chunk_entry(s, r)
    (root / "src" / "test").mkdir(parents=True)
    torch.save([entry], root / "src" / "test" / "000000.torch")
    (root / "src" / "evaluation_index.json").write_text(json.dumps({"room": INDEX}))
    convert_dataset(root / "src", root / "out", size=SIZE, progress=False)
    sample = dict(read_tar(next((root / "out" / "test").glob("*.tar"))))["room"]
    jpegs = [bytes(im.numpy().tobytes()) for im in entry["images"]]
    return sample, jpegs


def load(sample: dict, name: str) -> np.ndarray:
    return np.load(io.BytesIO(sample[name]))


def pixels(sample: dict) -> np.ndarray:
    names = ["ctx0.jpg", "ctx1.jpg", "tgt0.jpg", "tgt1.jpg", "tgt2.jpg"]
    return np.stack([np.asarray(Image.open(io.BytesIO(sample[n])), dtype=np.float64) for n in names])


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / np.mean((a - b) ** 2)))


def convert_one(src: Path, out: Path, fmt: str, **kw) -> tuple[dict, dict]:
    index = src.parent / "index.json"
    index.write_text(json.dumps({"room": INDEX}))
    manifest = convert_dataset(src, out, fmt, size=SIZE, eval_index=index, progress=False, **kw)
    samples = {k: v for shard in sorted((out / "test").glob("*.tar")) for k, v in read_tar(shard)}
    return manifest, samples


# ------------------------------------------------------------------------------------------------ round trips


def random_rigid(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    a = np.eye(4)
    a[:3, :3] = q * np.sign(np.linalg.det(q))
    a[:3, 3] = [0.3, -1.2, 2.0]
    return a


@pytest.mark.parametrize(
    "variant", ["nerfstudio", "nerfstudio_per_frame_file_order", "colmap_text", "colmap_binary"]
)
def test_captures_match_the_chunk_path(variant, scene, chunk_reference, tmp_path):
    """Cameras to 1e-5 and the same images (within one JPEG generation) as the chunk path's sample."""
    s, _ = scene
    reference, jpegs = chunk_reference
    c2w = s.extrinsics.double().numpy()
    k = s.intrinsics.double().numpy()
    src = tmp_path / "src"
    kw = {}
    if variant.startswith("nerfstudio"):
        per_frame = variant.endswith("file_order")
        export_nerfstudio(src / "room", jpegs, c2w, k, applied=random_rigid(4), per_frame=per_frame,
                          ext="jpg" if per_frame else "png")  # fmt: skip
        if per_frame:  # the file lists frames in reverse: its order reverses the indices
            kw["frame_order"] = "file"
        fmt = "nerfstudio"
    else:
        export_colmap(src / "room", jpegs, c2w, k, binary=variant == "colmap_binary")
        fmt = "colmap"
    index = dict(INDEX)
    if kw.get("frame_order") == "file":
        index = {key: [FRAMES - 1 - f for f in INDEX[key]] for key in ("context", "target")}
    (tmp_path / "index.json").write_text(json.dumps({"room": index}))
    manifest = convert_dataset(src, tmp_path / "out", fmt, size=SIZE, eval_index=tmp_path / "index.json",
                                progress=False, **kw)  # fmt: skip
    assert manifest["splits"]["test"]["refused"] == {} and manifest["splits"]["test"]["samples"] == 1
    sample = dict(read_tar(next((tmp_path / "out" / "test").glob("*.tar"))))["room"]
    np.testing.assert_allclose(load(sample, "extrinsics.npy"), load(reference, "extrinsics.npy"), atol=1e-5)
    np.testing.assert_allclose(load(sample, "intrinsics.npy"), load(reference, "intrinsics.npy"), atol=1e-6)
    meta = json.loads(sample["meta.json"])
    assert meta["scene"] == "room" and meta["context"] == index["context"] and meta["dataset"] == "src"
    error = np.abs(pixels(sample) - pixels(reference))
    assert error.mean() < 1.0 and error.max() < 40  # a PNG of the decoded JPEG: one more generation at most
    if variant in ("colmap_text", "colmap_binary"):
        assert error.max() == 0  # the same JPEG files: the same bytes in, the same sample out


def test_downscaled_image_folder_keeps_normalised_intrinsics(scene, chunk_reference, tmp_path):
    """DL3DV's layout: transforms.json describes the full images, --images images_2 reads half-size ones."""
    s, _ = scene
    reference, jpegs = chunk_reference
    half = []
    for data in jpegs:
        buf = io.BytesIO()
        Image.open(io.BytesIO(data)).resize((W // 2, H // 2), Image.Resampling.BOX).save(buf, format="PNG")
        half.append(buf.getvalue())
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    export_nerfstudio(tmp_path / "src" / "room", jpegs, c2w, k)  # full size in images/
    write_images(tmp_path / "src" / "room" / "images_2", half, "png")
    _, samples = convert_one(tmp_path / "src", tmp_path / "out", "nerfstudio", images="images_2")
    sample = samples["room"]
    np.testing.assert_allclose(load(sample, "intrinsics.npy"), load(reference, "intrinsics.npy"), atol=1e-6)
    assert psnr(pixels(sample), pixels(reference)) > 22  # the same view, from a quarter of the pixels

    # An image folder that is not a uniform down-scale is refused, not silently mis-calibrated.
    for name in sorted((tmp_path / "src" / "room" / "images_2").iterdir()):
        with Image.open(name) as im:
            stretched = im.resize((W // 2, H // 2 + 3))
        stretched.save(name)
    manifest, _ = convert_one(tmp_path / "src", tmp_path / "out2", "nerfstudio", images="images_2")
    assert manifest["splits"]["test"]["skips"] == {"image_size_mismatch": 1}
    assert "32x27" in manifest["splits"]["test"]["refused"]["room"]


# ------------------------------------------------------------------------------------------------- distortion


@pytest.fixture(scope="module")
def hires(scene):
    """The scene's frames rendered at 4x the size: what a lens sees, resampled once."""
    return render_scene(scene[0], 4 * H, 4 * W).images.numpy() * 255.0


def distort_image(hires: np.ndarray, k: np.ndarray, model: str, coeffs: tuple[float, ...]) -> np.ndarray:
    """A W x H image through an OpenCV lens, radial-tangential (k1, k2, p1, p2) or fisheye (k1..k4): each
    distorted pixel looks up the 4x pinhole render where its ray lands, found by fixed-point iteration."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    xd, yd = (u - k[0, 2] * W) / (k[0, 0] * W), (v - k[1, 2] * H) / (k[1, 1] * H)
    if model == "OPENCV":
        k1, k2, p1, p2 = coeffs
        x, y = xd.copy(), yd.copy()
        for _ in range(50):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            dx, dy = 2 * p1 * x * y + p2 * (r2 + 2 * x * x), p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = (xd - dx) / radial, (yd - dy) / radial
    else:  # theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8), theta_d the distorted radius
        theta_d = np.hypot(xd, yd)
        theta = theta_d.copy()
        for _ in range(50):
            theta = theta_d / (1 + sum(c * theta ** (2 * n + 2) for n, c in enumerate(coeffs)))
        scale = np.tan(theta) / np.maximum(theta_d, 1e-12)
        x, y = xd * scale, yd * scale
    f = hires.shape[0] // H
    uh = (x * k[0, 0] * W + k[0, 2] * W) * f - 0.5
    vh = (y * k[1, 1] * H + k[1, 2] * H) * f - 0.5
    grid = np.stack([uh / (hires.shape[1] - 1) * 2 - 1, vh / (hires.shape[0] - 1) * 2 - 1], -1)
    img = torch.from_numpy(hires).permute(2, 0, 1)[None].double()
    out = torch.nn.functional.grid_sample(
        img, torch.from_numpy(grid)[None], mode="bilinear", align_corners=True
    )
    return out[0].permute(1, 2, 0).numpy()


@pytest.mark.parametrize(
    "model, coeffs, floor",
    [("OPENCV", (-0.3, 0.08, 0.004, -0.003), 27.0), ("OPENCV_FISHEYE", (0.02, -0.01, 0.0, 0.0), 27.0)],
)
def test_distorted_images_are_undistorted(model, coeffs, floor, scene, hires, chunk_reference, tmp_path):
    """Frames rendered through a known lens come back to the chunk path's pinhole images. Measured: OPENCV
    (barrel, with tangential terms, as a COLMAP model) 28.0 dB, OPENCV_FISHEYE (as nerfstudio's
    transforms.json) 27.9 dB, against 29.2 dB with a lens of all-zero coefficients (the export's own
    resampling); ignoring the lens gives 18.2 and 18.0 dB. Asserted: above ``floor``, and ignoring under 20."""
    s, _ = scene
    reference, _ = chunk_reference
    k = s.intrinsics.double().numpy()
    distorted = []
    for f in range(FRAMES):
        buf = io.BytesIO()
        image = distort_image(hires[f], k, model, coeffs).round().clip(0, 255).astype(np.uint8)
        Image.fromarray(image).save(buf, "PNG")
        distorted.append(buf.getvalue())
    c2w = s.extrinsics.double().numpy()
    if model == "OPENCV":
        export_colmap(tmp_path / "lens" / "room", distorted, c2w, k, binary=True, model=model, extra=coeffs,
                      ext="png")  # fmt: skip
        export_colmap(tmp_path / "plain" / "room", distorted, c2w, k, binary=True, model="PINHOLE", ext="png")
        fmt = "colmap"
    else:
        lens = dict(zip(("k1", "k2", "k3", "k4"), coeffs))
        export_nerfstudio(tmp_path / "lens" / "room", distorted, c2w, k, model=model, distortion=lens)
        export_nerfstudio(tmp_path / "plain" / "room", distorted, c2w, k, model="PINHOLE")
        fmt = "nerfstudio"
    _, undistorted = convert_one(tmp_path / "lens", tmp_path / "out_lens", fmt)
    _, ignored = convert_one(tmp_path / "plain", tmp_path / "out_plain", fmt)
    # Both lenses bend inwards here: the pinhole camera keeps the source focal length (no zoom).
    np.testing.assert_allclose(load(undistorted["room"], "intrinsics.npy"), load(reference, "intrinsics.npy"),
                               atol=1e-6)  # fmt: skip
    good = psnr(pixels(undistorted["room"]), pixels(reference))
    bad = psnr(pixels(ignored["room"]), pixels(reference))
    assert good > floor and bad < 20.0, (good, bad)


def test_lens_models_follow_opencv():
    """Where a ray lands, by the formulas of OpenCV's documentation written out: the radial-tangential model
    (k1, k2, p1, p2, k3) and the fisheye (Kannala-Brandt) model, pixel centres at integers."""
    xy = torch.tensor([[0.3, -0.2], [-0.5, 0.4], [0.05, 0.6]], dtype=torch.float64)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    k1, k2, p1, p2, k3 = -0.2, 0.05, 0.003, -0.002, 0.01
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    cam = Camera("OPENCV", 64, 48, 50.0, 55.0, 32.5, 23.5, (k1, k2, p1, p2, k3))
    expect = torch.stack([50.0 * xd + 32.0, 55.0 * yd + 23.0], -1)
    torch.testing.assert_close(distorted_pixels(xy, cam), expect)

    theta = torch.atan(r2.sqrt())
    f1, f2, f3, f4 = 0.1, -0.02, 0.004, -0.001
    theta_d = theta * (1 + f1 * theta**2 + f2 * theta**4 + f3 * theta**6 + f4 * theta**8)
    scale = theta_d / r2.sqrt()
    fish = Camera("OPENCV_FISHEYE", 64, 48, 50.0, 55.0, 32.5, 23.5, (f1, f2, f3, f4))
    expect = torch.stack([50.0 * scale * x + 32.0, 55.0 * scale * y + 23.0], -1)
    torch.testing.assert_close(distorted_pixels(xy, fish), expect)


@pytest.mark.parametrize(
    "model, coeffs", [("OPENCV", (0.15, 0.05, 0.0, 0.0)), ("OPENCV_FISHEYE", (0.5, 0.3, 0.0, 0.0))]
)
def test_undistortion_zooms_until_no_pixel_is_blank(model, coeffs):
    """Pincushion (and fisheye) lenses leave the pinhole image's corners unseen at the source focal length:
    the focal length grows until every output pixel samples the source."""
    cam = Camera(model, 40, 30, 30.0, 30.0, 20.0, 15.0, coeffs)
    zoom = undistortion_zoom(cam)
    white = Image.new("RGB", (40, 30), (255, 255, 255))
    assert zoom > 1.01
    assert np.asarray(undistort(white, cam, zoom)).min() >= 254
    assert np.asarray(undistort(white, cam, 1.0)).min() < 200  # without the zoom the corners go blank


# --------------------------------------------------------------------------------------------------- refusals


def test_bad_scenes_are_refused_with_one_line_each_and_the_rest_convert(scene, chunk_reference, tmp_path):
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    src = tmp_path / "src"

    def edit(name: str, change) -> None:
        path = export_nerfstudio(src / name, jpegs, c2w, k, per_frame=name == "mixed_sizes")
        meta = json.loads(path.read_text())
        change(meta)
        path.write_text(json.dumps(meta))

    export_nerfstudio(src / "good", jpegs, c2w, k)
    edit("missing_image", lambda m: m["frames"][2].update(file_path="images/frame_00099.png"))
    edit("no_pose", lambda m: m["frames"][3].pop("transform_matrix"))
    edit("scaled_pose", lambda m: m["frames"][1].update(transform_matrix=(2 * np.array(
        m["frames"][1]["transform_matrix"])).tolist()))  # fmt: skip
    edit("nan_pose", lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")))
    edit("fisheye360", lambda m: m.update(camera_model="EQUIRECTANGULAR"))
    edit("mixed_sizes", lambda m: m["frames"][4].update(w=m["frames"][4]["w"] * 2, h=m["frames"][4]["h"] * 2,
                                                          fl_x=1.0, fl_y=1.0))  # fmt: skip
    (src / "mixed_sizes" / "images" / "frame_00003.png").unlink()
    Image.fromarray(np.zeros((2 * H, 2 * W, 3), np.uint8)).save(
        src / "mixed_sizes" / "images" / "frame_00003.png"
    )
    export_nerfstudio(src / "short", jpegs[:5], c2w[:5], k)
    (src / "no_capture").mkdir()
    export_colmap(src / "colmap_fov", jpegs, c2w, k, binary=False, model="PINHOLE")
    cams = src / "colmap_fov" / "sparse" / "0" / "cameras.txt"
    cams.write_text(cams.read_text().replace(" PINHOLE ", " FOV ").rstrip() + " 0.9\n")

    manifest = convert_dataset(src, tmp_path / "out", "nerfstudio", size=SIZE, context_gap=5, progress=False)
    test = manifest["splits"]["test"]
    assert test["scenes"] == 1 and test["samples"] == 1 and test["scenes_seen"] == 10
    assert test["skips"] == {
        "missing_image": 1, "missing_pose": 1, "bad_pose": 2, "unsupported_camera_model": 1,
        "mixed_image_sizes": 1, "too_few_frames": 1, "missing_capture_file": 2,
    }  # fmt: skip
    refused = test["refused"]
    assert set(refused) == {p.name for p in src.iterdir()} - {"good"}
    for name, message in refused.items():
        assert "\n" not in message and message.startswith(f"{name}:"), message
    assert "frame_00099.png does not exist" in refused["missing_image"]
    assert "no transform_matrix" in refused["no_pose"] and "not rigid" in refused["scaled_pose"]
    assert "NaN" in refused["nan_pose"] and "EQUIRECTANGULAR" in refused["fisheye360"]
    assert "5 frames" in refused["short"] and "--context-gap" in refused["short"]
    assert [p.name for p in (tmp_path / "out" / "test").glob("*.tar")] == ["test-good.tar"]

    colmap = convert_dataset(src, tmp_path / "out_colmap", "colmap", size=SIZE, context_gap=5, progress=False)
    fov = colmap["splits"]["test"]["refused"]["colmap_fov"]
    assert "FOV is not supported" in fov and "image_undistorter" in fov
    with pytest.raises(FileNotFoundError, match="one folder per scene"):
        convert_dataset(tmp_path / "absent", tmp_path / "x", "colmap", progress=False)


# ------------------------------------------------------------------------------------------------- evaluation


def test_generated_evaluation_samples_are_stated_and_repeatable(scene, chunk_reference, tmp_path):
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    export_colmap(tmp_path / "src" / "room", jpegs, c2w, k, binary=True)
    out = tmp_path / "out"
    manifest = convert_dataset(tmp_path / "src", out, "colmap", size=SIZE, context_gap=5, num_targets=3,
                                progress=False)  # fmt: skip
    files = [f"frame_{i:05d}.jpg" for i in (1, 6, 2, 4, 5)]
    stated = manifest["splits"]["test"]["evaluation_samples"]
    assert stated["room"]["context"] == [1, 6] and stated["room"]["target"] == [2, 4, 5]
    assert stated["room"]["files"] == files and stated["room"]["context_views"]["3"] == [1, 3, 6]
    assert evaluation_sample(8, 5, 3) == ((1, 6), (2, 4, 5))
    shard = out / "test" / "test-room.tar"
    stamp, digest = shard.stat().st_mtime_ns, manifest["splits"]["test"]["shards"][0]["sha256"]

    again = convert_dataset(tmp_path / "src", out, "colmap", size=SIZE, context_gap=5, progress=False)
    assert shard.stat().st_mtime_ns == stamp and again["splits"] == manifest["splits"]  # resumed, not redone
    (tmp_path / "samples.json").write_text(json.dumps(stated))
    indexed = convert_dataset(tmp_path / "src", tmp_path / "out2", "colmap", size=SIZE, progress=False,
                               eval_index=tmp_path / "samples.json")  # fmt: skip
    assert indexed["splits"]["test"]["shards"][0]["sha256"] == digest  # the stated samples repeat the shard
    other = convert_dataset(tmp_path / "src", out, "colmap", size=SIZE, context_gap=4, progress=False)
    assert other["splits"]["test"]["evaluation_samples"]["room"]["context"] == [1, 5]
    assert shard.stat().st_mtime_ns != stamp


def test_aesplat_test_runs_on_converted_captures(scene, chunk_reference, tmp_path, monkeypatch):
    from aesplat import cli

    monkeypatch.setenv("WANDB_MODE", "disabled")

    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    for name in ("room_a", "room_b"):
        export_colmap(tmp_path / "src" / name, jpegs, c2w, k, binary=True)
    convert_dataset(tmp_path / "src", tmp_path / "shards", "colmap", size=28, context_gap=5, progress=False)
    run = tmp_path / "run"
    cli.main(["test", "-c", str(REPO / "conf" / "smoke.yaml"), "--data.root", str(tmp_path / "shards"),
              "--trainer.default_root_dir", str(run)])  # fmt: skip
    summary = json.loads((run / "test-latest" / "summary.json").read_text())
    assert summary["num_scenes"] == 2 and summary["metrics"]["psnr"] > 5


@pytest.mark.parametrize("points", ["alternate", "none", "blank"])
def test_read_colmap_text_and_binary_agree(points, scene, chunk_reference, tmp_path):
    """Text models read every image whether their POINTS2D lines are there, missing, or padded with blanks."""
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    for binary in (False, True):
        export_colmap(
            tmp_path / str(binary) / "room",
            jpegs,
            c2w,
            k,
            binary=binary,
            model="RADIAL",
            extra=(0.01, -0.002),
            points=points,
        )
    text, binary = (read_colmap(tmp_path / name / "room") for name in ("False", "True"))
    np.testing.assert_allclose(text.c2w, c2w, atol=1e-6)  # the scene holds float32 rotations
    np.testing.assert_allclose(binary.c2w, text.c2w, atol=1e-12)
    np.testing.assert_allclose(binary.intrinsics, text.intrinsics, atol=1e-12)
    assert text.names == binary.names == [f"frame_{i:05d}.jpg" for i in range(FRAMES)]
    cameras = [read_colmap_cameras(tmp_path / name / "room" / "sparse" / "0" / f"cameras.{ext}")
               for name, ext in (("False", "txt"), ("True", "bin"))]  # fmt: skip
    assert cameras[0] == cameras[1]
    assert colmap_camera(*cameras[1][7], "room").distortion == (0.01, -0.002, 0.0, 0.0)


def test_to_shards_script_dispatches_on_format(scene, chunk_reference, tmp_path, capsys):
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    export_colmap(tmp_path / "src" / "room", jpegs, c2w, k, binary=False)
    (tmp_path / "src" / "empty").mkdir()
    to_shards = load_script("to_shards", DATA_PREP)
    to_shards.main(["--format", "colmap", "--src", str(tmp_path / "src"), "--out", str(tmp_path / "out"),
                    "--size", "16", "--context-gap", "4", "--num-targets", "2"])  # fmt: skip
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["test"]["samples"] == 1 and summary["test"]["skips"] == {"missing_capture_file": 1}
    assert captured.err.count("test/empty: skipped (missing_capture_file): empty:") == 1
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["config"]["context_gap"] == 4 and manifest["config"]["size"] == 16
    assert manifest["format"] == "colmap" and manifest["source_config"]["split"] == "test"
    assert manifest["splits"]["test"]["evaluation_samples"]["room"]["context"] == [1, 5]
    assert manifest["splits"]["test"]["evaluation_samples"]["room"]["target"] == [2, 4]
    with pytest.raises(SystemExit) as verdict:  # the chunk path's checksum verification reads this manifest too
        to_shards.main(["--verify", "--out", str(tmp_path / "out")])
    assert verdict.value.code == 0
    with pytest.raises(SystemExit, match="^to_shards.py: --eval-index picks test samples"):
        to_shards.main(["--format", "colmap", "--src", str(tmp_path / "src"), "--out", str(tmp_path / "o2"),
                        "--split", "train", "--eval-index", str(tmp_path / "index.json")])  # fmt: skip


def test_training_split_holds_whole_scenes_and_can_hold_some_out(scene, chunk_reference, tmp_path):
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    for name in ("room", "hall", "attic"):
        export_colmap(tmp_path / "src" / name, jpegs, c2w, k, binary=True)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", "colmap", size=16, split="train", min_gap=3,
                               progress=False)  # fmt: skip
    assert set(manifest["splits"]) == {"train"} and manifest["splits"]["train"]["frames"] == 3 * FRAMES
    raw = dict(read_tar(tmp_path / "out" / "train" / "train-room.tar"))["room"]
    assert json.loads(raw["meta.json"])["frames"] == list(range(FRAMES))
    np.testing.assert_allclose(load(raw, "extrinsics.npy"), c2w, atol=1e-5)
    held = convert_dataset(tmp_path / "src", tmp_path / "held", "colmap", size=16, split="train", min_gap=3,
                           val_scenes=1, progress=False)  # fmt: skip
    (key,) = held["splits"]["validation"]["held_out_from_train"]["scene_keys"]
    assert held["splits"]["train"]["scenes"] == 2 and held["splits"]["validation"]["scenes"] == 1
    assert key not in {k for s in held["splits"]["train"]["shards"] for k in s["scene_frames"]}


# ------------------------------------------------------------------------------------------- hostile captures


def test_a_capture_naming_files_outside_its_folder_is_refused(scene, chunk_reference, tmp_path):
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    secret = tmp_path / "src" / "secret.png"  # a file of the user's, beside the scene folders
    src = tmp_path / "src" / "scenes"
    for name, path in (("climbs", "../../secret.png"), ("absolute", str(secret))):
        meta_path = export_nerfstudio(src / name, jpegs, c2w, k)
        Image.open(io.BytesIO(jpegs[0])).save(secret)
        meta = json.loads(meta_path.read_text())
        meta["frames"][3]["file_path"] = path
        meta_path.write_text(json.dumps(meta))
    manifest = convert_dataset(src, tmp_path / "out", "nerfstudio", size=SIZE, context_gap=5, progress=False)
    refused = manifest["splits"]["test"]["refused"]
    assert manifest["splits"]["test"]["skips"] == {"path_outside_scene": 2}
    assert "../../secret.png lies outside the scene folder" in refused["climbs"]
    assert f"{secret} lies outside the scene folder" in refused["absolute"]
    export_colmap(tmp_path / "colmap" / "room", jpegs, c2w, k, binary=False)
    images = tmp_path / "colmap" / "room" / "sparse" / "0" / "images.txt"
    images.write_text(images.read_text().replace("frame_00002.jpg", "../../../secret.png"))
    manifest = convert_dataset(tmp_path / "colmap", tmp_path / "out2", "colmap", size=SIZE, context_gap=5,
                               progress=False)  # fmt: skip
    assert manifest["splits"]["test"]["skips"] == {"path_outside_scene": 1}
    escaped = convert_dataset(
        tmp_path / "colmap", tmp_path / "out3", "colmap", capture_path="../..", progress=False
    )
    assert "../.. lies outside the scene folder" in escaped["splits"]["test"]["refused"]["room"]


def test_a_frame_listed_twice_is_refused(scene, chunk_reference, tmp_path):
    """Two frames naming one image would let a context image also be a target."""
    s, _ = scene
    _, jpegs = chunk_reference
    c2w, k = s.extrinsics.double().numpy(), s.intrinsics.double().numpy()
    meta_path = export_nerfstudio(tmp_path / "src" / "room", jpegs, c2w, k)
    meta = json.loads(meta_path.read_text())
    meta["frames"].append({**meta["frames"][2], "file_path": "./" + meta["frames"][2]["file_path"]})
    meta_path.write_text(json.dumps(meta))
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", "nerfstudio", size=SIZE, context_gap=5,
                               progress=False)  # fmt: skip
    assert manifest["splits"]["test"]["skips"] == {"duplicate_frames": 1}
    assert "is listed twice" in manifest["splits"]["test"]["refused"]["room"]
