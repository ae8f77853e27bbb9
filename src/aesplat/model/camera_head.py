"""Camera head: VGGT's, as NAS3R uses it. The refined camera token of every view -> [T, quaternion (x, y, z, w),
fov_h, fov_w] (world-to-camera), turned into camera-to-world poses relative to view 0 and one focal length for
all views (view 0's, from its vertical field of view; square pixels, centred principal point)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from aesplat.geometry import DEFAULT_FOV, invert_pose, make_pose, quat_to_matrix

from .layers import Block, Mlp, init_weights

FOV_MIN, FOV_MAX = 0.09, 2.97  # radians: VGGT's clamp of the predicted fields of view (about 5° and 170°)
POSE_DIM = 9  # [T (3), quaternion x, y, z, w (4), fov_h, fov_w]

# The correlation branch works at a fixed resolution, so its cost does not grow with the input images.
CORRELATION_SIZE = 42  # images are resized to this square before the feature CNN
CORRELATION_RADIUS = (3, 6)  # searched displacements (rows, columns) in feature cells (stride 2: ±6, ±12 px)


def cost_volume(ref: Tensor, other: Tensor, radius: tuple[int, int]) -> Tensor:
    """Local correlation of two feature maps [N, C, h, w]: channel (dy + ry)·(2·rx + 1) + (dx + rx) of the
    result [N, (2·ry + 1)·(2·rx + 1), h, w] holds, at cell (i, j), the dot product of ``other[i, j]`` with
    ``ref[i + dy, j + dx]`` (zero outside ``ref``), for |dy| <= ry, |dx| <= rx."""
    ry, rx = radius
    h, w = other.shape[-2:]
    padded = F.pad(ref, (rx, rx, ry, ry))
    shifts = [(dy, dx) for dy in range(2 * ry + 1) for dx in range(2 * rx + 1)]
    return torch.stack([(other * padded[..., dy : dy + h, dx : dx + w]).sum(1) for dy, dx in shifts], dim=1)


class ViewCorrelation(nn.Module):
    """Correlation features between view 0 and every other view (off by default: ``camera_correlation``).

    A two-layer CNN (stride 2) embeds each view resized to 42×42; the cosine similarity of every feature cell
    of view i with the cells of view 0 around it (±3 rows, ±6 columns: ±6 and ±12 px at 42 px) forms a cost
    volume [(2·3+1)·(2·6+1) = 91, 21, 21], which two stride-2 convolutions and a linear layer turn into one
    vector per view. A dense match of this kind is what the camera token of a small, randomly initialised
    transformer does not learn from 3×3 patch tokens (``benchmarks/pose_probe.py``: supervised, the camera
    head's held-out rotation error stays at the no-rotation 6.29°, a CNN on the stacked pair does no better,
    and with this branch it falls to 2.82° in 2,000 steps). View 0's vector is zero (its pose is the identity
    by construction)."""

    def __init__(self, hidden: int, channels: int = 16) -> None:
        super().__init__()
        ry, rx = CORRELATION_RADIUS
        self.features = nn.Sequential(
            nn.Conv2d(3, channels, 3, 1, 1), nn.GELU(), nn.Conv2d(channels, channels, 3, 2, 1)
        )
        cells = (CORRELATION_SIZE + 1) // 2  # 21
        for _ in range(2):
            cells = (cells + 1) // 2  # 11, then 6
        self.reduce = nn.Sequential(
            nn.Conv2d((2 * ry + 1) * (2 * rx + 1), 32, 3, 2, 1),
            nn.GELU(),
            nn.Conv2d(32, 32, 3, 2, 1),
            nn.GELU(),
            nn.Flatten(),
            nn.Linear(32 * cells * cells, hidden),
        )

    def forward(self, images: Tensor) -> Tensor:
        """images [B, V, 3, H, W] in [0, 1] -> [B, V, hidden] (zeros for view 0)."""
        b, v = images.shape[:2]
        x = images.flatten(0, 1).float()
        if x.shape[-2:] != (CORRELATION_SIZE, CORRELATION_SIZE):
            x = F.interpolate(x, size=(CORRELATION_SIZE, CORRELATION_SIZE), mode="bilinear", antialias=True)
        f = F.normalize(self.features(x), dim=1, eps=1e-6).unflatten(0, (b, v))  # [B, V, C, h, w]
        ref, others = f[:, :1].expand(-1, v - 1, -1, -1, -1).flatten(0, 1), f[:, 1:].flatten(0, 1)
        volume = cost_volume(ref, others, CORRELATION_RADIUS)  # [B·(V-1), 91, h, w]
        out = self.reduce(volume).unflatten(0, (b, v - 1))
        return torch.cat([torch.zeros_like(out[:, :1]), out], dim=1)


class CameraHead(nn.Module):
    """VGGT's camera head (module and parameter names included, so trained heads load by name).

    The camera token of each view (index 0 of the last token map, [B, V, dim_in]) is normalised, modulated by
    an embedding of the current pose estimate (adaptive LayerNorm: shift, scale, gate), refined by
    ``trunk_depth`` transformer blocks over the views' tokens and mapped by an MLP to an update of the pose
    encoding [T, quaternion x, y, z, w, fov_h, fov_w] (the blocks attend across the views' camera tokens, masked
    as ``forward`` says). ``iterations`` refinements (NAS3R: 1), each from the
    previous estimate detached; the first from a learnt empty pose.

    A new head starts, as NAS3R's randomly initialised one does, at the identity rotation, zero translation
    and a field of view of 2·atan(0.5) (53°): the output layer's pose and FoV weights are zero.
    With ``correlation`` the vector of :class:`ViewCorrelation` is added to each normalised camera token
    (the images must then be given).
    """

    def __init__(self, dim_in: int, num_heads: int, trunk_depth: int = 4, iterations: int = 1,
                 correlation: bool = False) -> None:  # fmt: skip
        super().__init__()
        self.iterations = iterations
        self.trunk = nn.Sequential(
            *(Block(dim_in, num_heads, 4.0, 0.01, norm_eps=1e-5) for _ in range(trunk_depth))
        )
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, POSE_DIM))
        self.embed_pose = nn.Linear(POSE_DIM, dim_in)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, POSE_DIM)
        self.correlation = ViewCorrelation(dim_in) if correlation else None
        init_weights(self.trunk)
        with torch.no_grad():
            self.pose_branch.fc2.weight[:7].zero_()
            self.pose_branch.fc2.bias[:7].copy_(torch.tensor([0.0] * 6 + [1.0]) / iterations)
            self.pose_branch.fc2.weight[7:].zero_()
            self.pose_branch.fc2.bias[7:].fill_(DEFAULT_FOV / iterations)

    def encode(
        self, camera_tokens: Tensor, images: Tensor | None = None, num_context: int | None = None
    ) -> Tensor:
        """camera_tokens [B, V, dim_in] -> pose encoding [B, V, 9] of the last iteration (fields of view through
        a ReLU, as VGGT activates them; the next iteration starts from the encoding before it)."""
        tokens = self.token_norm(camera_tokens)
        if self.correlation is not None:
            if images is None:
                raise ValueError("the camera head's correlation branch needs the images of all views")
            tokens = tokens + self.correlation(images)
        b, v, _ = tokens.shape
        pose = None
        for _ in range(self.iterations):
            previous = self.empty_pose_tokens.expand(b, v, -1) if pose is None else pose.detach()
            condition = self.embed_pose(previous)
            shift, scale, gate = self.poseLN_modulation(condition).chunk(3, dim=-1)
            x = gate * (self.adaln_norm(tokens) * (1 + scale) + shift) + tokens
            for block in self.trunk:  # attention across the views' camera tokens
                x = block(x, num_context=num_context)
            delta = self.pose_branch(self.trunk_norm(x))
            pose = delta if pose is None else pose + delta
        return torch.cat([pose[..., :7], F.relu(pose[..., 7:])], dim=-1)  # VGGT: fields of view through a ReLU

    def forward(
        self,
        camera_tokens: Tensor,
        images: Tensor | None = None,
        aspect: float = 1.0,
        num_context: int | None = None,
    ) -> tuple[Tensor, Tensor]:
        """camera_tokens [B, V, dim_in] (images [B, V, 3, H, W] with ``correlation``) -> extrinsics
        [B, V, 4, 4] (camera-to-view-0; view 0 exactly the identity) and normalised intrinsics [B, V, 3, 3]
        of images of ``aspect`` = width / height.

        ``num_context``: the first ``num_context`` views are context views, whose tokens attend to context
        tokens only in the head's blocks (the others attend to all), as in the trunk's global attention, so the
        target views cannot change the context cameras. None: every token attends to every view (VGGT's and
        NAS3R's head, through which the targets reach the context cameras)."""
        return cameras_from_encoding(self.encode(camera_tokens, images, num_context), aspect)


def cameras_from_encoding(pose: Tensor, aspect: float) -> tuple[Tensor, Tensor]:
    """VGGT pose encoding [B, V, 9] (world-to-camera T and quaternion x, y, z, w; fov_h, fov_w) -> extrinsics
    [B, V, 4, 4] camera-to-world relative to view 0, intrinsics [B, V, 3, 3] normalised.

    As NAS3R: the fields of view are clamped to [0.09, 2.97] rad; fy = 0.5 / tan(fov_h / 2) (normalised by
    the height), fx the same focal in pixels (normalised by the width: fy / aspect); every view takes view
    0's focal; the principal point is the centre. fov_w is not used.
    """
    rot = quat_to_matrix(pose[..., [6, 3, 4, 5]])  # (x, y, z, w) -> (w, x, y, z)
    world_to_cam = make_pose(rot, pose[..., :3])
    rel = world_to_cam[:, :1] @ invert_pose(world_to_cam)  # camera i to world, then world to camera 0
    eye = torch.eye(4, dtype=rel.dtype, device=rel.device).expand_as(rel[:, :1])
    extrinsics = torch.cat([eye, rel[:, 1:]], dim=1)
    fov_h = pose[..., 7].clamp(FOV_MIN, FOV_MAX)[:, :1].expand(-1, pose.shape[1])  # view 0's, for all views
    fy = 0.5 / torch.tan(fov_h / 2)
    intrinsics = torch.zeros(*pose.shape[:2], 3, 3, dtype=pose.dtype, device=pose.device)
    intrinsics[..., 0, 0] = fy / aspect
    intrinsics[..., 1, 1] = fy
    intrinsics[..., 0, 2] = 0.5
    intrinsics[..., 1, 2] = 0.5
    intrinsics[..., 2, 2] = 1.0
    return extrinsics, intrinsics
