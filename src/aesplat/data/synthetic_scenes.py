"""Synthetic multi-view scenes: ray-cast analytic rooms along real-estate-like camera paths (docs/data.md).

An independent renderer (not the Gaussian rasterizer), so it can check the whole pipeline. A scene is a room
(six textured planes) holding boxes and spheres; the camera walks forward and turns like a house-tour video.
Each scene declares its effects and only those are computed:

- ``textures``  solid procedural textures (checkers + sinusoids); without it every surface is flat-coloured;
- ``specular``  Blinn-Phong highlights from a point light (they move with the view);
- ``exposure``  a smooth per-frame gain.

Every rendered frame also carries the magnitude of its specular term (zero for a scene without ``specular``), so
evaluation can score highlight pixels apart from the rest. ``PRESETS`` name matched data sets: ``specular``
(every scene and surface glossy) and ``diffuse`` (the same scenes, bit for bit, with the highlights off).

The diffuse radiance of a surface point is its albedo (no Lambert term), so a diffuse scene's pixel equals the
texture lookup at the point it sees. World axes: x right, y down, z forward (the camera's OpenCV axes at rest).
Depth is z-depth: rays are cast along d = R @ (x, y, 1), so the ray parameter is the depth itself.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from aesplat.geometry import project_points, unproject_depth

from .pixelsplat_chunks import cameras_to_row, encode_jpeg, write_chunk, write_index

EFFECTS = ("textures", "specular", "exposure")
DEFAULT_EFFECT_PROBS = {"textures": 1.0, "specular": 0.5, "exposure": 0.3}
DEFAULT_GLOSSY_FRACTION = 0.6  # share of surfaces with a highlight in a scene that declares ``specular``
# Matched data sets for the appearance ablation: every scene declares the same effects (no random draw), every
# surface is glossy. ``diffuse`` differs from ``specular`` only in not computing the highlight.
PRESETS = {
    "specular": {"effects": ("textures", "specular"), "glossy_fraction": 1.0},
    "diffuse": {"effects": ("textures",), "glossy_fraction": 1.0},
}
NUM_WAVES = 4  # sinusoids per texture
T_MIN = 1e-4  # rays start this far from the camera


@dataclass(frozen=True)
class Materials:
    """Per-surface appearance, S surfaces (6 room faces, then boxes, then spheres).

    color_a, color_b [S, 3] checker colours in [0, 1]; checker [S] cell size; offset [S, 3] texture phase;
    wave_dir [S, K, 3] sinusoid wave vectors (rad / unit); wave_phase [S, K]; wave_amp [S] modulation depth;
    ks [S] specular strength (0 = matte); shininess [S] Blinn-Phong exponent.
    """

    color_a: Tensor
    color_b: Tensor
    checker: Tensor
    offset: Tensor
    wave_dir: Tensor
    wave_phase: Tensor
    wave_amp: Tensor
    ks: Tensor
    shininess: Tensor


@dataclass(frozen=True)
class SyntheticScene:
    """One synthetic scene: geometry, materials, light, declared effects and its camera path.

    room_lo, room_hi [3]        the room's interior box (the camera path stays inside)
    box_lo, box_hi  [NB, 3]     axis-aligned boxes
    sphere_center [NS, 3], sphere_radius [NS]
    light [3] point-light position, light_color [3]
    extrinsics [F, 4, 4] camera-to-world; intrinsics [3, 3] normalised (shared by all frames)
    gains [F] exposure gain per frame (all ones unless ``exposure`` is declared)
    """

    key: str
    effects: frozenset[str]
    room_lo: Tensor
    room_hi: Tensor
    box_lo: Tensor
    box_hi: Tensor
    sphere_center: Tensor
    sphere_radius: Tensor
    materials: Materials
    light: Tensor
    light_color: Tensor
    extrinsics: Tensor
    intrinsics: Tensor
    gains: Tensor = field(default_factory=lambda: torch.ones(0))

    def __post_init__(self) -> None:
        unknown = set(self.effects) - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown effects {sorted(unknown)}; choose from {EFFECTS}")

    @property
    def num_frames(self) -> int:
        return self.extrinsics.shape[0]

    @property
    def num_surfaces(self) -> int:
        return 6 + self.box_lo.shape[0] + self.sphere_center.shape[0]


@dataclass(frozen=True)
class RenderedFrames:
    """Ray-cast frames: images [F, H, W, 3] float in [0, 1], depth [F, H, W] z-depth, surface [F, H, W] ids,
    points [F, H, W, 3] world hit points, normals [F, H, W, 3] unit normals facing the camera, specular
    [F, H, W] the magnitude of the specular term added to each pixel (its largest channel, times the exposure
    gain, averaged like the colour under supersampling, before clamping; zero without ``specular``)."""

    images: Tensor
    depth: Tensor
    surface: Tensor
    points: Tensor
    normals: Tensor
    specular: Tensor


# ----------------------------------------------------------------------------------------------- shading


def albedo(materials: Materials, points: Tensor, surface: Tensor, textured: bool) -> Tensor:
    """Texture lookup: world points [N, 3] on surfaces [N] -> albedo [N, 3] in [0, 1].

    Textures are solid (defined in 3D), so the same function serves planes, boxes and spheres.
    """
    a = materials.color_a[surface]
    if not textured:
        return a
    cell = torch.floor(points / materials.checker[surface, None] + materials.offset[surface])
    parity = torch.remainder(cell.sum(-1), 2.0)[:, None]  # [N, 1]
    base = a + (materials.color_b[surface] - a) * parity
    phase = (materials.wave_dir[surface] * points[:, None, :]).sum(-1) + materials.wave_phase[surface]
    wave = torch.sin(phase).mean(-1, keepdim=True)  # [N, 1] in [-1, 1]
    return (base * (1.0 + materials.wave_amp[surface, None] * wave)).clamp(0.0, 1.0)


def specular(scene: SyntheticScene, points: Tensor, normals: Tensor, surface: Tensor, origin: Tensor) -> Tensor:
    """Blinn-Phong highlight [N, 3] at world points [N, 3] with normals [N, 3], seen from ``origin`` [3]."""
    to_light = torch.nn.functional.normalize(scene.light - points, dim=-1)
    to_eye = torch.nn.functional.normalize(origin - points, dim=-1)
    half = torch.nn.functional.normalize(to_light + to_eye, dim=-1)
    n_dot_h = (normals * half).sum(-1).clamp_min(0.0)
    lit = (normals * to_light).sum(-1) > 0
    m = scene.materials
    strength = m.ks[surface] * n_dot_h ** m.shininess[surface] * lit
    return strength[:, None] * scene.light_color


# ----------------------------------------------------------------------------------------------- ray casting


def _safe(d: Tensor) -> Tensor:
    return torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)


def ray_directions(extrinsics: Tensor, intrinsics: Tensor, height: int, width: int) -> Tensor:
    """Per-pixel ray directions with unit camera z, [F, H*W, 3] in world space (ray parameter = z-depth)."""
    ys = (torch.arange(height, dtype=extrinsics.dtype) + 0.5) / height
    xs = (torch.arange(width, dtype=extrinsics.dtype) + 0.5) / width
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    k = intrinsics
    cam = torch.stack([(gx - k[0, 2]) / k[0, 0], (gy - k[1, 2]) / k[1, 1], torch.ones_like(gx)], dim=-1)
    return cam.reshape(1, -1, 3) @ extrinsics[:, :3, :3].transpose(-1, -2)


def cast_rays(scene: SyntheticScene, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest hit of rays origins [N, 3] + t * dirs [N, 3] -> t [N], surface id [N], normal [N, 3].

    The room encloses every ray (origins must lie inside it), so every ray hits something.
    """
    d = _safe(dirs)
    # Room interior: leave through the nearest of the six faces.
    t_faces = torch.where(dirs > 0, (scene.room_hi - origins) / d, (scene.room_lo - origins) / d)
    t, axis = t_faces.min(dim=-1)
    positive = torch.gather(dirs > 0, 1, axis[:, None])[:, 0]
    surface = 2 * axis + positive.long()
    normal = torch.nn.functional.one_hot(axis, 3).to(dirs.dtype) * torch.where(positive, -1.0, 1.0)[:, None]

    for b in range(scene.box_lo.shape[0]):
        t1 = (scene.box_lo[b] - origins) / d
        t2 = (scene.box_hi[b] - origins) / d
        t_near, near_axis = torch.minimum(t1, t2).max(dim=-1)
        t_far = torch.maximum(t1, t2).min(dim=-1).values
        hit = (t_near <= t_far) & (t_near > T_MIN) & (t_near < t)
        side = -torch.sign(torch.gather(dirs, 1, near_axis[:, None]))
        n_box = torch.nn.functional.one_hot(near_axis, 3).to(dirs.dtype) * side
        t = torch.where(hit, t_near, t)
        surface = torch.where(hit, 6 + b, surface)
        normal = torch.where(hit[:, None], n_box, normal)

    first_sphere = 6 + scene.box_lo.shape[0]
    for s in range(scene.sphere_center.shape[0]):
        oc = origins - scene.sphere_center[s]
        a = (dirs * dirs).sum(-1)
        half_b = (oc * dirs).sum(-1)
        c = (oc * oc).sum(-1) - scene.sphere_radius[s] ** 2
        disc = half_b * half_b - a * c
        t_s = (-half_b - disc.clamp_min(0.0).sqrt()) / a
        hit = (disc > 0) & (t_s > T_MIN) & (t_s < t)
        p = origins + t_s[:, None] * dirs
        n_s = (p - scene.sphere_center[s]) / scene.sphere_radius[s]
        t = torch.where(hit, t_s, t)
        surface = torch.where(hit, first_sphere + s, surface)
        normal = torch.where(hit[:, None], n_s, normal)
    return t, surface, normal


def _trace(scene: SyntheticScene, extrinsics: Tensor, height: int, width: int) -> tuple[Tensor, ...]:
    """Cast one ray per pixel centre of every frame: t, surface, normal, point, origin (flattened)."""
    dirs = ray_directions(extrinsics, scene.intrinsics, height, width)  # [F, HW, 3]
    origins = extrinsics[:, None, :3, 3].expand_as(dirs).reshape(-1, 3)
    dirs = dirs.reshape(-1, 3)
    t, surface, normal = cast_rays(scene, origins, dirs)
    return t, surface, normal, origins + t[:, None] * dirs, origins


def _shade(scene: SyntheticScene, surface: Tensor, normal: Tensor, points: Tensor, origins: Tensor) -> Tensor:
    """Radiance [N, 4] of hit points: RGB = the albedo, plus a highlight only if the scene declares
    ``specular``; channel 3 = the highlight's largest channel (0 without ``specular``)."""
    color = albedo(scene.materials, points, surface, textured="textures" in scene.effects)
    if "specular" not in scene.effects:
        return torch.cat([color, torch.zeros_like(color[:, :1])], dim=-1)
    highlight = specular(scene, points, normal, surface, origins)
    return torch.cat([color + highlight, highlight.amax(-1, keepdim=True)], dim=-1)


def render_scene(
    scene: SyntheticScene, height: int, width: int, frames: list[int] | None = None, supersample: int = 1
) -> RenderedFrames:
    """Ray-cast frames of a scene (all by default). Computes only the scene's declared effects.

    supersample: s > 1 averages s x s rays per pixel for the colour (box-filter anti-aliasing); depth,
    surface ids, points and normals always come from the pixel-centre ray.
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    idx = list(range(scene.num_frames)) if frames is None else list(frames)
    extr = scene.extrinsics[idx]
    f, s = len(idx), supersample
    t, surface, normal, points, origins = _trace(scene, extr, height, width)
    if s == 1:
        shaded = _shade(scene, surface, normal, points, origins).reshape(f, height, width, 4)
    else:
        _, sub_surface, sub_normal, sub_points, sub_origins = _trace(scene, extr, height * s, width * s)
        fine = _shade(scene, sub_surface, sub_normal, sub_points, sub_origins)
        shaded = fine.reshape(f, height, s, width, s, 4).mean(dim=(2, 4))
    if "exposure" in scene.effects:
        shaded = shaded * scene.gains[idx, None, None, None]
    color, highlight = shaded[..., :3], shaded[..., 3]
    shape = (f, height, width)
    return RenderedFrames(
        images=color.clamp(0.0, 1.0),
        specular=highlight,
        depth=t.reshape(shape),
        surface=surface.reshape(shape),
        points=points.reshape(*shape, 3),
        normals=normal.reshape(*shape, 3),
    )


# ----------------------------------------------------------------------------------------------- scene sampling


def look_pose(position: Tensor, yaw: Tensor, pitch: Tensor) -> Tensor:
    """Camera-to-world [F, 4, 4] for positions [F, 3] looking along yaw / pitch [F] (y-down world)."""
    forward = torch.stack(
        [torch.sin(yaw) * torch.cos(pitch), torch.sin(pitch), torch.cos(yaw) * torch.cos(pitch)], dim=-1
    )
    down = torch.tensor([0.0, 1.0, 0.0], dtype=position.dtype).expand_as(forward)
    right = torch.nn.functional.normalize(torch.linalg.cross(down, forward, dim=-1), dim=-1)
    down_cam = torch.linalg.cross(forward, right, dim=-1)  # camera y (down)
    pose = torch.eye(4, dtype=position.dtype).repeat(position.shape[0], 1, 1)
    pose[:, :3, :3] = torch.stack([right, down_cam, forward], dim=-1)
    pose[:, :3, 3] = position
    return pose


def _camera_path(
    rng: np.random.Generator, frames: int, half: np.ndarray, turn_scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """A house-tour path: walk forward, turn smoothly (the yaw's change along the path scaled by
    ``turn_scale``), bob slightly. Returns positions [F, 3], angles [F, 2]."""
    for _ in range(100):
        start = np.array(
            [rng.uniform(-0.5, 0.5) * half[0], rng.uniform(-0.15, 0.15), rng.uniform(-0.5, 0.5) * half[2]]
        )
        yaw0 = math.atan2(-start[0], -start[2]) + rng.uniform(-0.6, 0.6)  # roughly towards the room centre
        s = np.linspace(0.0, 1.0, frames)
        turn = rng.uniform(-0.9, 0.9)
        wobble = 0.08 * np.sin(2 * math.pi * rng.uniform(0.5, 1.5) * s + rng.uniform(0, 6.3))
        yaw = yaw0 + turn_scale * turn * s + turn_scale * wobble  # turn_scale 1: the same bits as unscaled
        pitch = rng.uniform(-0.15, 0.2) + 0.05 * np.sin(2 * math.pi * s + rng.uniform(0, 6.3))
        length = rng.uniform(1.5, 3.0)
        step = length / max(frames - 1, 1) * (1.0 + 0.2 * np.sin(2 * math.pi * s * rng.uniform(0.5, 2.0)))
        heading = np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], axis=-1)
        walked = np.cumsum(step[1:, None] * heading[1:], axis=0)  # integrate the heading along the walk
        pos = start + np.concatenate([np.zeros((1, 3)), walked])
        pos[:, 1] = start[1] + 0.03 * np.sin(2 * math.pi * 2.0 * s)
        # Stay inside, and keep at least 3.5 units of room ahead so no frame is just a wall filling the view.
        ahead = np.where(heading > 0, half - pos, half + pos)[:, [0, 2]] / np.abs(heading[:, [0, 2]]).clip(1e-6)
        if np.all(np.abs(pos[:, [0, 2]]) < half[[0, 2]] - 0.8) and ahead.min() > 3.5:
            return pos, np.stack([yaw, pitch], axis=-1)
    raise RuntimeError("could not fit a camera path into the room")


def _materials(
    rng: np.random.Generator, count: int, specular_fraction: float, texture_scale: float = 1.0
) -> Materials:
    hue = rng.uniform(0.15, 0.85, size=(count, 3))
    other = np.clip(
        hue * rng.uniform(0.4, 0.8, size=(count, 1)) + rng.uniform(-0.1, 0.1, size=(count, 3)), 0, 1
    )
    directions = rng.normal(size=(count, NUM_WAVES, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    freq = rng.uniform(3.0, 14.0, size=(count, NUM_WAVES, 1))
    glossy = rng.uniform(size=count) < specular_fraction
    to_t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return Materials(
        color_a=to_t(hue),
        color_b=to_t(other),
        checker=to_t(rng.uniform(0.25, 0.8, size=count) * texture_scale),
        offset=to_t(rng.uniform(0.1, 0.9, size=(count, 3))),
        wave_dir=to_t(directions * freq / texture_scale),
        wave_phase=to_t(rng.uniform(0, 2 * math.pi, size=(count, NUM_WAVES))),
        wave_amp=to_t(rng.uniform(0.15, 0.45, size=count)),
        ks=to_t(np.where(glossy, rng.uniform(0.4, 0.9, size=count), 0.0)),
        shininess=to_t(rng.uniform(20.0, 80.0, size=count)),
    )


def sample_scene(
    seed: int,
    frames: int,
    height: int,
    width: int,
    key: str | None = None,
    effects: tuple[str, ...] | None = None,
    effect_probs: dict[str, float] | None = None,
    texture_scale: float = 1.0,
    turn_scale: float = 1.0,
    glossy_fraction: float = DEFAULT_GLOSSY_FRACTION,
) -> SyntheticScene:
    """A random scene, fully determined by ``seed``. ``effects`` forces the declared effects; otherwise each
    effect is declared with its probability in ``effect_probs``. ``glossy_fraction``: the share of surfaces
    that get a highlight under ``specular`` (it changes no random draw, so the geometry stays the same)."""
    if frames < 3:
        raise ValueError(f"a scene needs at least 3 frames (two context views and a target), got {frames}")
    rng = np.random.default_rng(seed)
    probs = {**DEFAULT_EFFECT_PROBS, **(effect_probs or {})}
    if effects is None:
        effects = tuple(e for e in EFFECTS if rng.uniform() < probs[e])
    half = np.array([rng.uniform(3.0, 5.0), 1.4, rng.uniform(3.0, 5.0)])
    pos, angles = _camera_path(rng, frames, half, turn_scale)

    boxes, spheres = [], []
    want_boxes, want_spheres = int(rng.integers(3, 7)), int(rng.integers(1, 4))
    for _ in range(200):  # furniture placed away from the path (tries until the room is furnished)
        if len(boxes) >= want_boxes and len(spheres) >= want_spheres:
            break
        is_box = len(boxes) < want_boxes and (len(spheres) >= want_spheres or rng.uniform() < 0.6)
        size = rng.uniform(0.3, 0.9, size=3) if is_box else np.full(3, rng.uniform(0.25, 0.6))
        centre = np.array([rng.uniform(-1, 1) * (half[0] - size[0] - 0.1), half[1],
                           rng.uniform(-1, 1) * (half[2] - size[2] - 0.1)])  # fmt: skip
        clearance = np.linalg.norm(pos[:, [0, 2]] - centre[[0, 2]], axis=-1).min()
        if clearance < np.linalg.norm(size[[0, 2]]) + 0.5:
            continue
        if is_box:  # standing on the floor (y = half[1], y points down)
            boxes.append((centre - [size[0], 2 * size[1], size[2]], centre + [size[0], 0.0, size[2]]))
        else:  # resting on the floor or floating above it
            centre[1] = half[1] - size[0] - rng.uniform(0.0, 1.0)
            spheres.append((centre, size[0]))

    n_surfaces = 6 + len(boxes) + len(spheres)
    materials = _materials(rng, n_surfaces, specular_fraction=glossy_fraction, texture_scale=texture_scale)
    fov_x = math.radians(rng.uniform(55.0, 75.0))
    fx = 0.5 / math.tan(fov_x / 2)
    intrinsics = torch.tensor([[fx, 0.0, 0.5], [0.0, fx * width / height, 0.5], [0.0, 0.0, 1.0]])
    s = np.linspace(0.0, 1.0, frames)
    gains = np.exp(0.25 * np.sin(2 * math.pi * rng.uniform(0.3, 1.0) * s + rng.uniform(0, 6.3)))
    light = np.array([rng.uniform(-0.5, 0.5) * half[0], -half[1] + 0.3, rng.uniform(-0.5, 0.5) * half[2]])
    f32 = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    pos_t, ang_t = f32(pos), f32(angles)
    return SyntheticScene(
        key=key or f"synthetic_{seed:08d}",
        effects=frozenset(effects),
        room_lo=f32(-half),
        room_hi=f32(half),
        box_lo=f32([b[0] for b in boxes]).reshape(-1, 3),
        box_hi=f32([b[1] for b in boxes]).reshape(-1, 3),
        sphere_center=f32([c for c, _ in spheres]).reshape(-1, 3),
        sphere_radius=f32([r for _, r in spheres]).reshape(-1),
        materials=materials,
        light=f32(light),
        light_color=f32([1.0, 0.97, 0.9]),
        extrinsics=look_pose(pos_t, ang_t[:, 0], ang_t[:, 1]),
        intrinsics=intrinsics,
        gains=f32(gains if "exposure" in effects else np.ones(frames)),
    )


# ----------------------------------------------------------------------------------------------- data set


def view_overlap(
    depth: Tensor, extrinsics: Tensor, intrinsics: Tensor, i: int, j: int, tol: float = 0.02
) -> float:
    """Covisibility of frames i and j from ground-truth depth [F, H, W]: the mean over both directions of the
    fraction of pixels that reproject inside the other view with a consistent depth (relative ``tol``)."""
    h, w = depth.shape[-2:]
    k = intrinsics.expand(2, 3, 3)[None]
    fractions = []
    for a, b in ((i, j), (j, i)):
        pts = unproject_depth(depth[a][None, None], k[:, :1], extrinsics[a][None, None]).reshape(1, -1, 3)
        uv, z, valid = project_points(pts, k[:, :1], extrinsics[b][None, None], h, w)
        uv, z, valid = uv[0, 0], z[0, 0], valid[0, 0]
        col = uv[:, 0].long().clamp(0, w - 1)
        row = uv[:, 1].long().clamp(0, h - 1)
        seen = depth[b][row, col]
        consistent = valid & ((z - seen).abs() < tol * seen)
        fractions.append(consistent.float().mean().item())
    return float(np.mean(fractions))


def recommended_gaps(frames: int) -> tuple[int, int]:
    """Context-gap range (frames) suited to synthetic paths of ``frames`` frames."""
    lo = max(2, frames // 6)
    return lo, max(lo, (2 * frames) // 3)


def scene_to_chunk_entry(scene: SyntheticScene, rendered: RenderedFrames, jpeg_quality: int = 95) -> dict:
    """A rendered scene as a chunk dict in the real field layout, plus ``depths`` [F, H, W], ``effects`` and
    ``specular`` float16 [F, H, W], the specular term's magnitude per pixel (all zero without ``specular``)."""
    images = (rendered.images * 255.0).round().to(torch.uint8).numpy()
    return {
        "url": f"synthetic://{scene.key}",
        "timestamps": torch.arange(scene.num_frames, dtype=torch.int64) * 33_333,
        "cameras": cameras_to_row(scene.extrinsics, scene.intrinsics.expand(scene.num_frames, 3, 3)),
        "images": [encode_jpeg(img, jpeg_quality) for img in images],
        "key": scene.key,
        "depths": rendered.depth.clone(),
        "effects": sorted(scene.effects),
        "specular": rendered.specular.to(torch.float16),
    }


# Where each split's scene seeds start (scene i of split S has seed ``seed * 10_000_019 + offset + i``) and
# the seed of its evaluation-index draw: disjoint streams, so adding validation scenes changes no train or
# test scene, and no test context/target draw.
SPLIT_SEEDS = {"train": (0, None), "test": (1_000_000, 7_919), "validation": (2_000_000, 7_927)}


def _write_splits(out: Path, counts: dict[str, int], frames: int, height: int, width: int, seed: int,
                  scenes_per_chunk: int, scene_options: dict, jpeg_quality: int, supersample: int,
                  eval_index: dict[str, dict], bar) -> None:  # fmt: skip
    """Write each split of ``counts`` (train, test, validation) into ``out/<split>``; the held-out splits'
    evaluation entries (two context views, three targets between them) go into ``eval_index[split]``."""
    lo, hi = recommended_gaps(frames)
    for split, count in counts.items():
        offset, eval_seed = SPLIT_SEEDS[split]
        eval_rng = None if eval_seed is None else np.random.default_rng(seed + eval_seed)
        split_dir = out / split
        split_dir.mkdir(parents=True, exist_ok=True)
        index: dict[str, str] = {}
        for start in range(0, count, scenes_per_chunk):
            chunk = []
            for i in range(start, min(count, start + scenes_per_chunk)):
                scene_seed = seed * 10_000_019 + offset + i
                scene = sample_scene(scene_seed, frames, height, width, key=f"{split}{seed:03d}_{i:05d}",
                                     **scene_options)  # fmt: skip
                rendered = render_scene(scene, height, width, supersample=supersample)
                chunk.append(scene_to_chunk_entry(scene, rendered, jpeg_quality))
                if eval_rng is not None:
                    gap = int(eval_rng.integers(max(lo, 4), max(hi, 4) + 1))  # room for three targets
                    c0 = int(eval_rng.integers(0, frames - gap))
                    targets = sorted(eval_rng.choice(np.arange(c0 + 1, c0 + gap), size=3, replace=False))
                    overlap = view_overlap(rendered.depth, scene.extrinsics, scene.intrinsics, c0, c0 + gap)
                    eval_index.setdefault(split, {})[scene.key] = {
                        "context": [c0, c0 + gap], "target": [int(t) for t in targets],
                        "overlap": round(overlap, 4)}  # fmt: skip
                bar.update()
            name = f"{start // scenes_per_chunk:06d}.torch"
            write_chunk(chunk, split_dir / name)
            index.update({entry["key"]: name for entry in chunk})
        write_index(split_dir, index)


def generate_dataset(
    out: str | Path,
    scenes: int = 24,
    frames: int = 32,
    height: int = 96,
    width: int = 128,
    seed: int = 0,
    test_scenes: int | None = None,
    val_scenes: int | None = None,
    scenes_per_chunk: int = 4,
    effect_probs: dict[str, float] | None = None,
    jpeg_quality: int = 95,
    supersample: int = 1,
    texture_scale: float = 1.0,
    turn_scale: float = 1.0,
    effects: tuple[str, ...] | None = None,
    glossy_fraction: float = DEFAULT_GLOSSY_FRACTION,
    preset: str | None = None,
    progress: bool = False,
) -> dict:
    """Write a synthetic data set in the chunk format: ``out/{train,validation,test}/*.torch`` + ``index.json``,
    ``out/evaluation_index.json`` for the test scenes and ``out/validation_index.json`` for the validation
    scenes (two context views, three targets between them, overlap from depth), and ``out/dataset.json``
    (sizes, the recommended context-gap range and depth range for model.net.near / far).

    ``scenes`` is the number of training scenes; ``test_scenes`` defaults to half of it (at least 1),
    ``val_scenes`` to a third of the test scenes (0: no validation split). The three splits come from disjoint
    seed streams: the train and test scenes (and the test evaluation index) are the same whatever
    ``val_scenes`` is, and no validation scene is a train or test scene.
    ``supersample`` s > 1 anti-aliases the images with s x s rays per pixel (about s^2 times slower).
    ``effects`` declares the same effects in every scene (else each is drawn with ``effect_probs``);
    ``glossy_fraction`` is the share of glossy surfaces; ``preset`` (a key of ``PRESETS``: ``specular`` or
    ``diffuse``) sets both. The same seed gives the same geometry, materials and cameras under either preset.
    Returns the ``dataset.json`` contents.
    """
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
        if effects is not None or effect_probs:
            raise ValueError(f"preset {preset!r} fixes the effects; do not also pass effects or effect_probs")
        effects, glossy_fraction = PRESETS[preset]["effects"], PRESETS[preset]["glossy_fraction"]
    if not 0.0 <= glossy_fraction <= 1.0:
        raise ValueError(f"glossy_fraction must lie in [0, 1], got {glossy_fraction}")
    if min(scenes, frames, height, width, scenes_per_chunk) < 1:
        raise ValueError("scenes, frames, height, width and scenes_per_chunk must be positive")
    if frames < 5:
        raise ValueError(f"--frames must be at least 5 (context pair with three targets between), got {frames}")
    out = Path(out)
    n_test = max(1, (scenes + 1) // 2) if test_scenes is None else test_scenes
    n_val = n_test // 3 if val_scenes is None else val_scenes
    if n_val < 0:
        raise ValueError(f"val_scenes must be >= 0, got {n_val}")
    counts = {"train": scenes, "test": n_test, **({"validation": n_val} if n_val else {})}
    eval_index: dict[str, dict] = {}
    from tqdm import tqdm

    bar = tqdm(total=sum(counts.values()), desc="synthetic scenes", disable=not progress)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small element-wise kernels: extra threads only spin (10x slower on a busy CPU)
    try:
        scene_options = {"effect_probs": effect_probs, "texture_scale": texture_scale, "turn_scale": turn_scale,
                         "effects": effects, "glossy_fraction": glossy_fraction}  # fmt: skip
        _write_splits(out, counts, frames, height, width, seed, scenes_per_chunk, scene_options, jpeg_quality,
                      supersample, eval_index, bar)  # fmt: skip
    finally:
        torch.set_num_threads(threads)
        bar.close()
    for split, name in (("test", "evaluation_index.json"), ("validation", "validation_index.json")):
        if counts.get(split):
            (out / name).write_text(json.dumps(eval_index.get(split, {}), indent=1, sort_keys=True))
    lo, hi = recommended_gaps(frames)
    info = {
        "dataset": "synthetic",
        "seed": seed,
        "frames": frames,
        "height": height,
        "width": width,
        "supersample": supersample,
        "texture_scale": texture_scale,
        "turn_scale": turn_scale,
        "preset": preset,
        "effects": None if effects is None else sorted(effects),
        "glossy_fraction": glossy_fraction,
        "train_scenes": scenes,
        "test_scenes": n_test,
        "validation_scenes": n_val,
        "gap_range": [lo, hi],
        "near": 0.1,
        "far": 10.0,
    }
    (out / "dataset.json").write_text(json.dumps(info, indent=1))
    return info
