"""Exports round-trip: predict -> COLMAP / nerfstudio -> this project's capture readers give the same cameras;
``.splat`` read back by a reader written from the format's description gives the same Gaussians within 8-bit
quantisation; bad inputs are one line and write nothing."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from aesplat.data.sources.colmap import read_colmap
from aesplat.data.sources.nerfstudio import read_nerfstudio
from aesplat.errors import UserError
from aesplat.export import (
    PredictedScene,
    parse_formats,
    read_ply,
    read_prediction,
    write_colmap,
    write_nerfstudio,
    write_ply,
    write_splat,
)
from aesplat.export.command import main as export_main
from aesplat.geometry import C0, make_pose, quat_to_matrix
from aesplat.types import Gaussians
from tests.prediction_helpers import make_prediction, split_image

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")


@pytest.fixture(scope="module")
def prediction(tmp_path_factory):
    out, _, _ = make_prediction(tmp_path_factory.mktemp("predict"), "--export", "colmap,nerfstudio,splat")
    return out


def random_scene(tmp_path, views: int = 3, n: int = 40) -> PredictedScene:
    """Cameras far from the identity (rotations, translations, fx != fy, off-centre principal points)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(1)
    quats = torch.randn(views, 4, generator=g)
    ext = make_pose(quat_to_matrix(quats), torch.randn(views, 3, generator=g) * 2)
    intr = torch.eye(3).repeat(views, 1, 1)
    intr[:, 0, 0], intr[:, 1, 1] = 0.7 + torch.rand(views, generator=g), 0.9 + torch.rand(views, generator=g)
    intr[:, 0, 2], intr[:, 1, 2] = 0.4 + 0.2 * torch.rand(views, generator=g), 0.45 + 0.1 * torch.rand(views)
    images = [split_image(tmp_path / f"{i:02d}_v{i}.png", 10 + i, size=20) for i in range(views)]
    gaussians = Gaussians(torch.randn(1, n, 3), torch.randn(1, n, 4), torch.rand(1, n, 3) * 0.1 + 0.01,
                          torch.rand(1, n), torch.randn(1, n, 4, 3))  # fmt: skip
    return PredictedScene(tmp_path, [f"v{i}" for i in range(views)], images, ext, intr, 20, 20,
                          ext[:0], intr[:0], gaussians, torch.zeros(3))  # fmt: skip


def assert_same_cameras(capture, scene: PredictedScene) -> None:
    assert [Path(name).name for name in capture.names] == [p.name for p in scene.images]
    np.testing.assert_allclose(capture.c2w, scene.extrinsics.double().numpy(), atol=1e-5, rtol=0)
    np.testing.assert_allclose(capture.intrinsics, scene.intrinsics.double().numpy(), atol=1e-5, rtol=0)
    for path, src in zip(capture.files, scene.images):
        assert path.read_bytes() == src.read_bytes()


def test_colmap_export_reads_back_the_same_cameras(tmp_path):
    scene = random_scene(tmp_path / "src")
    write_colmap(scene, tmp_path / "colmap")
    assert_same_cameras(read_colmap(tmp_path / "colmap"), scene)
    points = np.loadtxt(tmp_path / "colmap" / "sparse" / "0" / "points3D.txt", comments="#")
    np.testing.assert_allclose(points[:, 1:4], scene.gaussians.means[0].numpy(), rtol=1e-6)
    rgb = np.clip(0.5 + C0 * scene.gaussians.sh[0, :, 0].numpy(), 0, 1) * 255
    np.testing.assert_allclose(points[:, 4:7], rgb, atol=0.5 + 1e-3)


def test_nerfstudio_export_reads_back_the_same_cameras(tmp_path):
    scene = random_scene(tmp_path / "src")
    write_nerfstudio(scene, tmp_path / "ns")
    assert_same_cameras(read_nerfstudio(tmp_path / "ns"), scene)
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    # OpenGL camera axes: the camera looks down its -z column
    forward = -np.asarray(meta["frames"][1]["transform_matrix"])[:3, 2]
    np.testing.assert_allclose(forward, scene.extrinsics[1, :3, 2].numpy(), atol=1e-6)
    cloud = (tmp_path / "ns" / meta["ply_file_path"]).read_bytes()
    body = cloud[cloud.index(b"end_header\n") + 11 :]
    table = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    np.testing.assert_array_equal(table["xyz"], scene.gaussians.means[0].numpy())


def read_splat(path) -> dict[str, np.ndarray]:
    """The ``.splat`` layout, from its description: 32-byte records of position 3 x float32, scale 3 x float32,
    RGBA 4 x uint8, rotation 4 x uint8 (value = (byte - 128) / 128)."""
    raw = np.frombuffer(path.read_bytes(), dtype=np.uint8).reshape(-1, 32)
    rgba = raw[:, 24:28].astype(np.float64) / 255
    rot = (raw[:, 28:32].astype(np.float64) - 128) / 128
    return {
        "position": raw[:, 0:12].copy().view("<f4"),
        "scale": raw[:, 12:24].copy().view("<f4"),
        "rgb": rgba[:, :3],
        "opacity": rgba[:, 3],
        "rotation": rot / np.linalg.norm(rot, axis=1, keepdims=True),
    }


def test_splat_reads_back_within_8_bit_quantisation(tmp_path):
    n = 500
    quats = torch.randn(1, n, 4)
    quats[0, 0] = 0.0  # degenerate: written as the identity
    g = Gaussians(torch.randn(1, n, 3), quats, torch.rand(1, n, 3) + 1e-3, torch.rand(1, n),
                  torch.randn(1, n, 9, 3))  # fmt: skip
    s = read_splat(write_splat(tmp_path / "g.splat", g))
    assert len(s["position"]) == n and (tmp_path / "g.splat").stat().st_size == 32 * n
    np.testing.assert_array_equal(s["position"], g.means[0].numpy())
    np.testing.assert_array_equal(s["scale"], g.scales[0].numpy())
    rgb = np.clip(0.5 + C0 * g.sh[0, :, 0].double().numpy(), 0, 1)
    np.testing.assert_allclose(s["rgb"], rgb, atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(s["opacity"], g.opacities[0].double().numpy(), atol=0.5 / 255 + 1e-7)
    q = (g.quats[0] / g.quats[0].norm(dim=1, keepdim=True)).double().numpy()
    q[0] = [1, 0, 0, 0]
    # the same rotation (q or -q) to within the 1/128 steps of each component
    err = np.minimum(np.abs(s["rotation"] - q).max(1), np.abs(s["rotation"] + q).max(1))
    assert err.max() < 2.5 / 128


def test_predict_export_round_trips(prediction):
    scene = read_prediction(prediction)
    assert_same_cameras(read_colmap(prediction / "colmap"), scene)
    assert_same_cameras(read_nerfstudio(prediction / "nerfstudio"), scene)
    s = read_splat(prediction / "gaussians.splat")
    ply = read_ply(prediction / "gaussians.ply")
    np.testing.assert_array_equal(s["position"], ply.means[0].numpy())
    np.testing.assert_allclose(s["scale"], ply.scales[0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(s["opacity"], ply.opacities[0].numpy(), atol=0.5 / 255 + 1e-6)
    # the predicted colours are the input pixels' (red and blue halves)
    assert {tuple(c) for c in np.round(s["rgb"] * 255).astype(int)} <= {(220, 30, 30), (30, 30, 220)}


def test_export_after_the_fact_writes_the_same_files(prediction, tmp_path):
    import shutil

    copy = tmp_path / "pred"
    shutil.copytree(prediction, copy, ignore=shutil.ignore_patterns("colmap", "nerfstudio", "*.splat"))
    assert export_main([str(copy), "--formats", "splat,colmap"]) == 0
    assert (copy / "gaussians.splat").read_bytes() == (prediction / "gaussians.splat").read_bytes()
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        rel = f"colmap/sparse/0/{name}"
        assert (copy / rel).read_text() == (prediction / rel).read_text()
    assert not (copy / "nerfstudio").exists()
    assert not [p for p in copy.iterdir() if p.name.startswith(".")]  # no staging folder left behind


def test_export_refuses_what_exists_and_writes_nothing(prediction, tmp_path, capsys):
    import shutil

    copy = tmp_path / "pred"
    shutil.copytree(prediction, copy, ignore=shutil.ignore_patterns("nerfstudio"))
    before = sorted(p.relative_to(copy) for p in copy.rglob("*"))
    with pytest.raises(SystemExit, match=r"^aesplat export: .*colmap exists; remove it, or give --overwrite"):
        export_main([str(copy), "--formats", "nerfstudio,colmap"])
    assert sorted(p.relative_to(copy) for p in copy.rglob("*")) == before  # nerfstudio/ not written either
    (copy / "colmap" / "sparse" / "0" / "cameras.txt").write_text("stale")
    assert export_main([str(copy), "--formats", "colmap", "--overwrite"]) == 0
    assert "PINHOLE" in (copy / "colmap" / "sparse" / "0" / "cameras.txt").read_text()


def test_bad_inputs_are_one_line(tmp_path):
    with pytest.raises(UserError, match="unknown export format 'ply'; choose from colmap, nerfstudio, splat"):
        parse_formats("colmap,ply")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match=r"holds no prediction \(no cameras.json, gaussians.ply, inputs\)"):
        export_main([str(tmp_path / "empty")])
    assert not list((tmp_path / "empty").iterdir())
    with pytest.raises(SystemExit, match="is not a folder"):
        export_main([str(tmp_path / "nowhere")])


def test_predict_refuses_an_unknown_export_before_writing(tmp_path):
    from aesplat.predict import main

    out = tmp_path / "pred"
    with pytest.raises(SystemExit, match="unknown export format 'obj'"):
        main(["--ckpt", str(tmp_path / "missing.ckpt"), "--out", str(out), "--export", "obj", "a.png", "b.png"])
    assert not out.exists()


# ----------------------------------------------------------------------------------------------- PLY reader


def test_read_ply_inverts_write_ply(tmp_path):
    g = Gaussians(torch.randn(1, 30, 3), torch.randn(1, 30, 4), torch.rand(1, 30, 3) + 0.01,
                  torch.rand(1, 30) * 0.9 + 0.05, torch.randn(1, 30, 16, 3))  # fmt: skip
    back = read_ply(write_ply(tmp_path / "g.ply", g))
    torch.testing.assert_close(back.means, g.means, rtol=0, atol=0)
    torch.testing.assert_close(back.sh, g.sh, rtol=0, atol=0)
    torch.testing.assert_close(back.scales, g.scales, rtol=1e-6, atol=0)
    torch.testing.assert_close(back.opacities, g.opacities, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(back.quats, g.quats / g.quats.norm(dim=-1, keepdim=True), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n", "format ascii 1.0"),
        (
            "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nend_header\n",
            "uchar red",
        ),
        (
            "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n",
            "not a 3DGS PLY of the reference layout .no f_dc_0",
        ),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 1\nelement face 1\nend_header\n", "vertices"),
        ("solid cube\n", "not a PLY file"),
    ],
)
def test_read_ply_refuses_other_layouts_in_one_line(tmp_path, header, message):
    path = tmp_path / "other.ply"
    path.write_bytes(header.encode() + b"\0" * 64)
    with pytest.raises(UserError, match=message) as err:
        read_ply(path)
    assert "\n" not in str(err.value)


def test_read_ply_refuses_a_truncated_file(tmp_path):
    g = Gaussians(torch.randn(1, 5, 3), torch.randn(1, 5, 4), torch.rand(1, 5, 3), torch.rand(1, 5),
                  torch.randn(1, 5, 1, 3))  # fmt: skip
    data = write_ply(tmp_path / "g.ply", g).read_bytes()
    (tmp_path / "g.ply").write_bytes(data[:-10])
    with pytest.raises(UserError, match="truncated"):
        read_ply(tmp_path / "g.ply")
    assert math.isfinite(read_ply(write_ply(tmp_path / "h.ply", g)).opacities.sum().item())
