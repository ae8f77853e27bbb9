"""scripts/splat_viewer_check.py: GaussianSplats3D (npm) in headless Chromium draws a prediction's exports as
this project's renderer draws them, on a synthetic prediction whose answer is known.

The prediction is well-behaved where the demo's is not: two textured flat patches (a tilted wall and a card in
front of it) of a few thousand overlapping Gaussians, each about 1 x 2 pixels, anisotropic and turned every
way within its patch, over a coloured background that shows round them. Camera 0 is turned and moved, its
principal point is off centre and its pixel focal lengths differ, so that any slip in pose, axes, field of view,
principal point or background costs far more than the threshold: drawn right, both files score 42.9-44.6 dB
against the SH-0 render; with cy mirrored, no principal point, fy taken from fx, a 10 % wider field of view,
the camera turned about its z axis, the pose inverted or the background left black, 10-19 dB; half a pixel
off, 30-32 dB; the 2D filter of the other rasterize mode, 34-37 dB.
"""

import importlib.util
import json
import math
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torch import Tensor

from aesplat.camera_path import camera_record
from aesplat.export import write_ply
from aesplat.export.splat import write_splat
from aesplat.geometry import make_pose, matrix_to_quat, rgb_to_sh_dc
from aesplat.images import save_image
from aesplat.predict import compact_json
from aesplat.render import RenderSettings, render
from aesplat.types import Gaussians
from tests.helpers import need
from tests.script_loader import load_script

check = load_script("splat_viewer_check")
WIDTH, HEIGHT = 64, 48
INTRINSICS = torch.tensor([[0.95, 0.0, 0.46], [0.0, 1.2, 0.54], [0.0, 0.0, 1.0]])  # fx 61 px, fy 58 px
BACKGROUND = (0.15, 0.25, 0.45)
MIN_PSNR_DB = 40.0


def rotation(axis: list[float], degrees: float) -> Tensor:
    """[3, 3] float64: a turn of ``degrees`` about ``axis`` (Rodrigues)."""
    k = torch.tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    angle = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def patch(centre: list[float], turn: Tensor, half: float, step: float, colour, generator: torch.Generator):
    """Gaussians on a square grid of spacing ``step`` over a flat square patch, in camera 0's frame: centres
    [N, 3], rotations [N, 3, 3], standard deviations [N, 3] (1.6 and 0.9 steps in the patch, 0.1 across it)
    and colours [N, 3] (``colour`` of the patch coordinates in [-1, 1]^2). ``turn``'s columns are the patch's
    axes and normal."""
    side = torch.linspace(-half, half, int(2 * half / step) + 1, dtype=torch.float64)
    u, v = torch.meshgrid(side, side, indexing="xy")
    uv = torch.stack([u.flatten(), v.flatten()], dim=-1)  # [N, 2]
    means = torch.tensor(centre, dtype=torch.float64) + uv @ turn[:, :2].T
    angle = torch.rand(len(uv), generator=generator, dtype=torch.float64) * math.pi  # turned within the patch
    in_patch = torch.zeros(len(uv), 3, 3, dtype=torch.float64)
    in_patch[:, 0, 0], in_patch[:, 0, 1] = angle.cos(), -angle.sin()
    in_patch[:, 1, 0], in_patch[:, 1, 1] = angle.sin(), angle.cos()
    in_patch[:, 2, 2] = 1.0
    scales = torch.tensor([1.6 * step, 0.9 * step, 0.1 * step], dtype=torch.float64).expand(len(uv), 3)
    return means, turn @ in_patch, scales, colour(uv / half)


def wall_colour(uv: Tensor) -> Tensor:  # a gradient over a coarse checker
    checker = ((uv[:, 0] * 4).floor() + (uv[:, 1] * 3).floor()) % 2
    return torch.stack([0.2 + 0.3 * (uv[:, 0] + 1), 0.3 + 0.4 * checker, 0.8 - 0.25 * (uv[:, 1] + 1)], dim=-1)


def card_colour(uv: Tensor) -> Tensor:  # two halves, shaded top to bottom
    u, v = uv.unbind(-1)
    return torch.stack([0.9 - 0.15 * (v + 1), 0.55 + 0.3 * (u > 0), torch.full_like(u, 0.15)], dim=-1)


def synthetic_prediction(out: Path, rasterize_mode: str) -> tuple[Path, int]:
    """A folder laid out as ``aesplat predict --export splat`` writes it, one view; returns it and its count of
    Gaussians. Their SH carry a degree-1 band, so predict's render (every band) and the SH-0 render differ."""
    generator = torch.Generator().manual_seed(0)
    camera_to_world = make_pose(
        rotation([0.3, 1.0, 0.2], 20.0), torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64)
    )
    parts = [
        patch([0.1, 0.1, 3.0], rotation([0.2, 1.0, 0.0], 35.0), 1.1, 0.04, wall_colour, generator),
        patch([-0.3, -0.25, 2.2], rotation([1.0, 0.3, 0.0], -25.0), 0.35, 0.03, card_colour, generator),
    ]
    means, turns, scales, rgb = (torch.cat(column) for column in zip(*parts))
    turn, shift = camera_to_world[:3, :3], camera_to_world[:3, 3]
    n = len(means)
    sh = torch.zeros(n, 4, 3, dtype=torch.float64)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    sh[:, 1:] = 0.15 * torch.randn(n, 3, 3, generator=generator, dtype=torch.float64)
    gaussians = Gaussians(
        means=(means @ turn.T + shift)[None],
        quats=matrix_to_quat(turn @ turns)[None],
        scales=scales[None],
        opacities=torch.full((1, n), 0.9, dtype=torch.float64),
        sh=sh[None],
    ).to(dtype=torch.float32)
    extrinsics = camera_to_world.float()
    options = asdict(RenderSettings(rasterize_mode=rasterize_mode))
    image = render(gaussians, extrinsics[None, None], INTRINSICS[None, None], HEIGHT, WIDTH,
                   background=torch.tensor(BACKGROUND), **options).color[0, 0]  # fmt: skip
    for folder in ("renders", "inputs"):
        save_image(image, out / folder / "00_synthetic.png")
    write_ply(out / "gaussians.ply", gaussians)
    write_splat(out / "gaussians.splat", gaussians)
    cameras = {
        "views": [{"image": "synthetic", **camera_record(extrinsics, INTRINSICS, HEIGHT, WIDTH)}],
        "render": {"background": list(BACKGROUND), "options": options},
    }
    (out / "cameras.json").write_text(compact_json(cameras))
    return out, n


@pytest.mark.slow  # Chromium and a web page (npm's registry the first time): about 6 s per mode here
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_the_viewer_draws_both_files_as_aesplat_renders_them(tmp_path, rasterize_mode):
    need(check.find_chromium() is not None, "Chromium (scripts/install_chromium.sh)")
    need(shutil.which("npm") is not None, "npm (Node.js)")
    need(importlib.util.find_spec("websockets") is not None, 'websockets (pip install -e ".[viewer]")')
    pred, count = synthetic_prediction(tmp_path / "pred", rasterize_mode)

    assert check.main(["--pred", str(pred)]) == 0
    out = pred / "splat-viewer-check"
    record = json.loads((out / "splat_viewer_check.json").read_text())
    assert record["image_size"] == [WIDTH, HEIGHT]
    assert record["viewer_settings"]["antialiased"] == (rasterize_mode == "antialiased")
    assert record["camera0_gaussians"]["below_viewer_size_floor"] == 0
    assert set(record["files"]) == {"splat", "ply"}
    for name, result in record["files"].items():
        assert result["gaussians_in_file"] == result["gaussians_loaded"] == count, name
        psnr = result["psnr_db"]
        assert psnr["vs_sh0_render"] > MIN_PSNR_DB, (name, psnr)
        assert psnr["vs_predict_render"] < psnr["vs_sh0_render"] - 3, (name, psnr)  # the SH-1 band shows
        picture = np.asarray(Image.open(out / result["screenshot"]))
        assert picture.shape == (HEIGHT, WIDTH, 3)
        assert (np.abs(picture[0, 0].astype(int) - np.multiply(BACKGROUND, 255)) <= 1).all()  # a bare corner


def test_a_folder_without_the_exports_is_one_line(tmp_path):
    with pytest.raises(SystemExit) as missing:
        check.main(["--pred", str(tmp_path / "nowhere")])
    assert "is not a folder" in str(missing.value) and "\n" not in str(missing.value)

    pred, _ = synthetic_prediction(tmp_path / "pred", "classic")
    (pred / "gaussians.splat").unlink()
    with pytest.raises(SystemExit) as no_splat:
        check.main(["--pred", str(pred)])
    assert "--export splat" in str(no_splat.value) and "\n" not in str(no_splat.value)
    assert not (pred / "splat-viewer-check").exists()
