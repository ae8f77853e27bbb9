"""Synthetic scenes: texture lookup, moving highlights, depth consistent with the cameras, chunk format."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from aesplat.data import synthetic_scenes
from aesplat.data.pixelsplat_chunks import cameras_to_row, list_chunks, load_chunk, row_to_cameras
from aesplat.data.synthetic_scenes import albedo, generate_dataset, render_scene, sample_scene
from aesplat.geometry import project_points, unproject_depth

H, W = 40, 56


def test_diffuse_pixels_equal_texture_lookup_and_never_compute_specular(monkeypatch):
    def forbidden(*args, **kwargs):
        raise AssertionError("the specular term was evaluated for a scene that does not declare it")

    monkeypatch.setattr(synthetic_scenes, "specular", forbidden)
    scene = sample_scene(11, frames=4, height=H, width=W, effects=("textures",))
    out = render_scene(scene, H, W)
    # Exactly the texture lookup at the hit points.
    lookup = albedo(scene.materials, out.points.reshape(-1, 3), out.surface.reshape(-1), textured=True)
    assert torch.equal(out.images.reshape(-1, 3), lookup)
    # And at the points recovered from depth + cameras (checker edges may flip under float error).
    pts = unproject_depth(out.depth[None], scene.intrinsics.expand(1, 4, 3, 3), scene.extrinsics[None])[0]
    from_depth = albedo(scene.materials, pts.reshape(-1, 3), out.surface.reshape(-1), textured=True)
    close = (from_depth - out.images.reshape(-1, 3)).abs().amax(-1) < 1e-3
    assert close.float().mean() > 0.98
    # The textured image is not flat, and without `textures` every surface is its flat colour.
    assert out.images.reshape(-1, 3).std(0).min() > 0.02
    flat = render_scene(replace(scene, effects=frozenset()), H, W)
    assert torch.equal(flat.images.reshape(-1, 3), scene.materials.color_a[flat.surface.reshape(-1)])


def test_declared_specular_changes_the_image():
    """Declaring `specular` adds the highlight to the image: light is only added, visibly, and it is the
    specular term wherever the sum stays below 1 (where the image clips, less is added)."""
    scene = sample_scene(2, frames=3, height=8, width=8, effects=("specular",), glossy_fraction=1.0)
    shiny = render_scene(scene, 8, 8)
    matte = render_scene(replace(scene, effects=frozenset()), 8, 8)
    added = shiny.images - matte.images  # [F, H, W, 3]
    assert (added >= 0).all() and added.amax() > 0.1 and (added.amax(-1) > 1e-3).float().mean() > 0.1
    unclipped = (shiny.images < 1 - 1e-6).all(-1)
    torch.testing.assert_close(added.amax(-1)[unclipped], shiny.specular[unclipped].float(), atol=1e-5, rtol=0)


def test_specular_highlight_moves_between_views():
    scene = sample_scene(5, frames=16, height=H, width=W, effects=("textures", "specular"))
    glossy = replace(scene.materials, ks=torch.full_like(scene.materials.ks, 0.8),
                     shininess=torch.full_like(scene.materials.shininess, 40.0))  # fmt: skip
    scene = replace(scene, materials=glossy, light_color=torch.full((3,), 0.4))
    diffuse = render_scene(replace(scene, effects=frozenset({"textures"})), H, W, frames=[0, 15])
    shiny = render_scene(scene, H, W, frames=[0, 15])
    highlight = (shiny.images - diffuse.images).sum(-1)  # [2, H, W]
    peaks = []
    for v in range(2):
        flat = highlight[v].flatten().argmax()
        assert highlight[v].flatten()[flat] > 0.1
        peaks.append(shiny.points[v].reshape(-1, 3)[flat])
    assert torch.linalg.norm(peaks[0] - peaks[1]) > 0.05
    # The diffuse part is view-independent: the same surface point has the same albedo in both views.
    assert highlight.min() >= -1e-6


def test_depth_agrees_with_cameras():
    scene = sample_scene(7, frames=10, height=H, width=W, effects=("textures",))
    out = render_scene(scene, H, W, frames=[2, 6])
    extr = scene.extrinsics[[2, 6]][None]  # [1, 2, 4, 4]
    intr = scene.intrinsics.expand(1, 2, 3, 3)
    pts = unproject_depth(out.depth[None], intr, extr)[0, 0].reshape(1, -1, 3)  # view 0 -> world
    uv, z, valid = project_points(pts, intr[:, 1:], extr[:, 1:], H, W)  # -> view 1
    uv, z, valid = uv[0, 0], z[0, 0], valid[0, 0]
    assert valid.float().mean() > 0.3
    # The four pixel centres around each projection bound the depth and colour seen there.
    corner = (uv[valid] - 0.5).floor().long()
    cols = torch.stack([corner[:, 0], corner[:, 0] + 1], -1).clamp(0, W - 1)[:, [0, 1, 0, 1]]
    rows = torch.stack([corner[:, 1], corner[:, 1] + 1], -1).clamp(0, H - 1)[:, [0, 0, 1, 1]]
    seen = out.depth[1][rows, cols]  # [N, 4]
    zv = z[valid]
    consistent = (zv >= seen.amin(-1) * 0.995) & (zv <= seen.amax(-1) * 1.005)
    occluded = zv > seen.amax(-1) * 1.005  # something nearer hides the point in view 1
    assert consistent.float().mean() > 0.95
    assert (~consistent & ~occluded).float().mean() < 0.03  # seen "through" a surface: only at silhouettes
    colours = out.images[1][rows, cols]  # [N, 4, 3]
    own = out.images[0].reshape(-1, 3)[valid]
    inside = (own >= colours.amin(1) - 0.02) & (own <= colours.amax(1) + 0.02)
    assert inside.all(-1)[consistent].float().mean() > 0.9  # the rest: checker edges between pixel centres


def test_supersampling_averages_subpixel_rays():
    scene = sample_scene(8, frames=3, height=8, width=12, effects=("textures",))
    fine = render_scene(scene, 16, 24)
    coarse = render_scene(scene, 8, 12, supersample=2)
    pooled = fine.images.reshape(3, 8, 2, 12, 2, 3).mean(dim=(2, 4))
    assert torch.allclose(coarse.images, pooled, atol=1e-6)
    assert torch.equal(coarse.depth, render_scene(scene, 8, 12).depth)  # geometry from the pixel centre


def test_scene_is_deterministic_from_seed():
    a = render_scene(sample_scene(9, frames=4, height=16, width=16), 16, 16)
    b = render_scene(sample_scene(9, frames=4, height=16, width=16), 16, 16)
    c = render_scene(sample_scene(10, frames=4, height=16, width=16), 16, 16)
    assert torch.equal(a.images, b.images) and torch.equal(a.depth, b.depth)
    assert not torch.equal(a.images, c.images)


def test_texture_scale_stretches_every_texture_feature():
    base = sample_scene(3, frames=3, height=8, width=8, effects=("textures",))
    wide = sample_scene(3, frames=3, height=8, width=8, effects=("textures",), texture_scale=3.0)
    points = torch.rand(4000, 3) * 4.0 - 2.0
    surface = torch.randint(0, base.num_surfaces, (4000,))
    near = albedo(base.materials, points, surface, textured=True)
    far = albedo(wide.materials, points * 3.0, surface, textured=True)
    # The same texture three times larger (checker edges may flip under float rounding) ...
    assert ((near - far).abs().amax(-1) < 1e-4).float().mean() > 0.99
    # ... and not the same texture at the same scale.
    assert (near - albedo(wide.materials, points, surface, textured=True)).abs().mean() > 0.02
    assert torch.equal(base.extrinsics, wide.extrinsics)  # only the textures change


def _yaw(extrinsics: torch.Tensor) -> torch.Tensor:
    forward = extrinsics[:, :3, 2]  # camera z axis in the world (y down): heading angle about y
    return torch.atan2(forward[:, 0], forward[:, 2])


def test_turn_scale_scales_how_far_a_path_turns():
    frames = 12
    turning = [sample_scene(s, frames=frames, height=8, width=8).extrinsics for s in range(6)]
    straight = [sample_scene(s, frames=frames, height=8, width=8, turn_scale=0.0).extrinsics for s in range(6)]
    assert max((_yaw(e) - _yaw(e)[0]).abs().max() for e in turning) > 0.2  # some default path turns
    for e in straight:  # the heading never changes; the camera still walks and bobs
        assert torch.allclose(_yaw(e), _yaw(e)[:1].expand(frames), atol=1e-5)
        assert torch.linalg.norm(e[-1, :3, 3] - e[0, :3, 3]) > 1.0
    same = sample_scene(0, frames=frames, height=8, width=8, turn_scale=1.0).extrinsics
    assert torch.equal(same, turning[0])


def test_exposure_scales_frames():
    scene = sample_scene(4, frames=6, height=16, width=16, effects=("exposure",))
    base = render_scene(replace(scene, effects=frozenset()), 16, 16)
    out = render_scene(scene, 16, 16)
    expected = (base.images * scene.gains[:, None, None, None]).clamp(0, 1)
    assert torch.allclose(out.images, expected)
    assert scene.gains.std() > 0.01


def test_camera_rows_round_trip():
    scene = sample_scene(1, frames=5, height=H, width=W)
    rows = cameras_to_row(scene.extrinsics, scene.intrinsics.expand(5, 3, 3))
    assert rows.dtype == torch.float32 and rows.shape == (5, 18)
    assert torch.all(rows[:, 4:6] == 0)
    c2w, k = row_to_cameras(rows)
    assert np.allclose(c2w, scene.extrinsics.numpy(), atol=1e-5)
    assert np.allclose(k, scene.intrinsics.expand(5, 3, 3).numpy(), atol=1e-7)


def test_generate_dataset_writes_chunk_format(tmp_path):
    info = generate_dataset(tmp_path, scenes=3, test_scenes=2, frames=8, height=16, width=24, seed=1,
                            scenes_per_chunk=2)  # fmt: skip
    assert info["train_scenes"] == 3 and info["test_scenes"] == 2
    for split, n in (("train", 3), ("test", 2)):
        index = json.loads((tmp_path / split / "index.json").read_text())
        assert len(index) == n
        chunks = list_chunks(tmp_path / split)
        assert len(chunks) == (n + 1) // 2
        scene = load_chunk(chunks[0])[0]
        assert set(scene) >= {"url", "timestamps", "cameras", "images", "key", "depths"}
        assert scene["timestamps"].dtype == torch.int64 and scene["timestamps"].shape == (8,)
        assert scene["cameras"].dtype == torch.float32 and scene["cameras"].shape == (8, 18)
        assert len(scene["images"]) == 8 and scene["images"][0].dtype == torch.uint8
        assert bytes(scene["images"][0][:2].tolist()) == b"\xff\xd8"  # JPEG magic
        assert scene["depths"].shape == (8, 16, 24)
        assert index[scene["key"]] == chunks[0].name
    evaluation = json.loads((tmp_path / "evaluation_index.json").read_text())
    assert len(evaluation) == 2
    for entry in evaluation.values():
        c0, c1 = entry["context"]
        assert 0 <= c0 < c1 < 8 and all(c0 < t < c1 for t in entry["target"])
        assert 0.0 <= entry["overlap"] <= 1.0


def test_generate_rejects_too_few_frames(tmp_path):
    with pytest.raises(ValueError, match="frames"):
        generate_dataset(tmp_path, scenes=1, frames=3)


def test_rendered_specular_magnitude_is_the_highlight_term():
    scene = sample_scene(5, frames=6, height=H, width=W, effects=("textures", "specular"), glossy_fraction=1.0)
    out = render_scene(scene, H, W, frames=[0, 5])
    origins = scene.extrinsics[[0, 5], None, None, :3, 3].expand_as(out.points).reshape(-1, 3)
    term = synthetic_scenes.specular(scene, out.points.reshape(-1, 3), out.normals.reshape(-1, 3),
                              out.surface.reshape(-1), origins)  # fmt: skip
    assert torch.allclose(out.specular.reshape(-1), term.amax(-1), atol=1e-6)
    assert (out.specular > 0.05).any()
    diffuse = render_scene(replace(scene, effects=frozenset({"textures"})), H, W, frames=[0, 5])
    assert torch.equal(diffuse.specular, torch.zeros(2, H, W))
    # The image is the diffuse image plus the term (before clamping), wherever it does not saturate.
    unclipped = (out.images < 1).all(-1)
    added = (out.images - diffuse.images).amax(-1)
    assert torch.allclose(added[unclipped], out.specular[unclipped], atol=1e-5)
    # Supersampled: the magnitude is averaged over the sub-pixel rays like the colour.
    fine = render_scene(scene, 2 * H, 2 * W, frames=[0])
    coarse = render_scene(scene, H, W, frames=[0], supersample=2)
    assert torch.allclose(coarse.specular[0], fine.specular[0].reshape(H, 2, W, 2).mean((1, 3)), atol=1e-5)


def test_presets_are_the_same_scenes_with_and_without_highlights(tmp_path):
    sets = {}
    for preset in ("specular", "diffuse"):
        info = generate_dataset(tmp_path / preset, scenes=2, test_scenes=2, frames=6, height=16, width=24,
                                seed=4, preset=preset)  # fmt: skip
        assert info["preset"] == preset and info["glossy_fraction"] == 1.0
        sets[preset] = [s for split in ("train", "test") for c in list_chunks(tmp_path / preset / split)
                        for s in load_chunk(c)]  # fmt: skip
    for shiny, matte in zip(sets["specular"], sets["diffuse"]):
        assert shiny["effects"] == ["specular", "textures"] and matte["effects"] == ["textures"]
        assert torch.equal(shiny["cameras"], matte["cameras"]) and torch.equal(shiny["depths"], matte["depths"])
        assert shiny["specular"].dtype == torch.float16 and shiny["specular"].shape == (6, 16, 24)
        assert torch.equal(matte["specular"], torch.zeros(6, 16, 24, dtype=torch.float16))
    assert any((s["specular"] > 0.05).any() for s in sets["specular"])
    for name in ("evaluation_index.json",):
        assert (tmp_path / "specular" / name).read_text() == (tmp_path / "diffuse" / name).read_text()
    with pytest.raises(ValueError, match="preset"):
        generate_dataset(tmp_path / "x", scenes=1, frames=6, preset="shiny")
    with pytest.raises(ValueError, match="fixes the effects"):
        generate_dataset(tmp_path / "x", scenes=1, frames=6, preset="diffuse", effect_probs={"specular": 1.0})


def test_glossy_fraction_changes_only_which_surfaces_shine():
    a = sample_scene(9, frames=4, height=8, width=8, effects=("specular",), glossy_fraction=0.6)
    b = sample_scene(9, frames=4, height=8, width=8, effects=("specular",), glossy_fraction=1.0)
    assert torch.equal(a.extrinsics, b.extrinsics) and torch.equal(a.box_lo, b.box_lo)
    assert torch.equal(a.materials.color_a, b.materials.color_a)
    assert (b.materials.ks > 0).all() and (a.materials.ks == 0).any()
    glossy = a.materials.ks > 0
    assert torch.equal(a.materials.ks[glossy], b.materials.ks[glossy])
