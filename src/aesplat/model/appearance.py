"""Decoupled appearance (paper section 4): I2DC for the zeroth-order SH coefficient, and a view-dependent
head fed with GVSRE and the warped colour map (WCM) for the higher-order coefficients.

``i2dc``, ``gvsre_descriptor`` and ``warped_color_map`` are pure functions; the small networks (the GVSRE MLP,
pool's colour embedding and the view-dependent head) are the model's ``appearance`` parameter group.

How the head takes in the other context views is the *view aggregation* (``VIEW_AGGREGATIONS``):

concat  the paper's head: the GVSRE descriptor of every context camera and the WCM of every other context view,
        concatenated in view order, so the head's width fixes the number of context views when it is built.
pool    beyond the paper: each camera's GVSRE relation and each other view's warped colour are embedded by
        MLPs shared by all views and averaged over the views (the colours over the views that see the
        Gaussian only), so one set of weights serves 2..N views in any order of the non-reference views.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from aesplat.errors import UserError
from aesplat.geometry import num_sh_coeffs, project_points, rgb_to_sh_dc, safe_norm


@dataclass(frozen=True)
class AppearanceMode:
    """Where an appearance mode (a row of the paper's ablation) takes each Gaussian's SH coefficients from."""

    dc: Literal["i2dc", "gaussian_head"]  # the zeroth order (l = 0)
    higher: Literal["view_dependent_head", "gaussian_head", "none"]  # l >= 1; none: SH degree 0
    gvsre: bool = False  # the view-dependent head sees GVSRE
    wcm: bool = False  # the view-dependent head sees the WCM


# The view-dependent head always sees the Gaussian head's features, besides GVSRE / WCM as a mode says.
APPEARANCE_MODES: dict[str, AppearanceMode] = {
    "full": AppearanceMode("i2dc", "view_dependent_head", gvsre=True, wcm=True),
    "no_gvsre": AppearanceMode("i2dc", "view_dependent_head", wcm=True),
    "no_wcm": AppearanceMode("i2dc", "view_dependent_head", gvsre=True),
    "i2dc_only": AppearanceMode("i2dc", "none"),
    "baseline": AppearanceMode("gaussian_head", "gaussian_head"),
    "baseline_i2dc": AppearanceMode("i2dc", "gaussian_head"),
}


def appearance_mode(name: str) -> AppearanceMode:
    """The entry of ``APPEARANCE_MODES`` called ``name``; ValueError naming the choices if there is none."""
    if name not in APPEARANCE_MODES:
        raise ValueError(f"unknown appearance {name!r}; choose one of {', '.join(APPEARANCE_MODES)}")
    return APPEARANCE_MODES[name]


def i2dc(images: Tensor) -> Tensor:
    """Image-to-Direct-Component: pixels [B, V, 3, H, W] -> DC coefficients [B, V·H·W, 1, 3].

    c0 = (C - 0.5) / C0, Gaussians in (view, row, column) order. No parameters.
    """
    b = images.shape[0]
    return rgb_to_sh_dc(images.permute(0, 1, 3, 4, 2).reshape(b, -1, 1, 3))


def gvsre_descriptor(means: Tensor, camera_centres: Tensor, min_distance: float = 1e-4) -> Tensor:
    """Gaussian-to-views spatial relation: for each Gaussian and each context camera centre o, the unit
    direction (o - mu) / |o - mu| and log |o - mu| (distance clamped to ``min_distance``).

    means [B, N, 3], camera_centres [B, C, 3] -> [B, N, 4·C], camera by camera [dx, dy, dz, log d].
    A Gaussian at a camera centre gets direction 0 and log(min_distance), finite with finite gradients.
    """
    diff = camera_centres[:, None] - means[:, :, None]  # [B, N, C, 3]
    dist = safe_norm(diff, keepdim=True).clamp_min(min_distance)  # [B, N, C, 1]
    desc = torch.cat([diff / dist, dist.log()], dim=-1)  # [B, N, C, 4]
    return desc.flatten(2)


def other_views(v: int, device: torch.device | None = None) -> Tensor:
    """[V, V-1]: row p lists the views other than p in increasing order (the WCM's order)."""
    return torch.tensor([[q for q in range(v) if q != p] for p in range(v)], dtype=torch.long, device=device)


def masked_mean(x: Tensor, mask: Tensor) -> Tensor:
    """Mean of x [..., V, D] over the views where mask [..., V] is non-zero -> [..., D]; 0 where none is.

    Views outside the mask take no part at all, not even a NaN or Inf they hold (a ``where`` before the sum).
    """
    keep = mask[..., None] > 0
    total = torch.where(keep, x, torch.zeros_like(x)).sum(-2)
    return total / keep.sum(-2).to(x.dtype).clamp_min(1.0)


def warped_color_map(
    means: Tensor, images: Tensor, intrinsics: Tensor, extrinsics: Tensor
) -> tuple[Tensor, Tensor]:
    """WCM: project each Gaussian centre of context view p into every other context view q and sample q's
    image there bilinearly.

    means [B, V, P, 3] (world frame, P = H·W per view), images [B, V, 3, H, W], intrinsics [B, V, 3, 3]
    (normalised), extrinsics [B, V, 4, 4] camera-to-world.
    Returns colours [B, V, P, V-1, 3] and validity mask [B, V, P, V-1] (1 where the point is in front of q,
    z > 0, and inside q's image), with the other views q in increasing order. Invalid samples are colour 0.
    """
    b, v, p, _ = means.shape
    if v < 2:
        raise ValueError(f"the warped colour map needs at least 2 context views, got {v}")
    h, w = images.shape[-2:]
    # uv [B, Vq, Vp·P, 2], valid [B, Vq, Vp·P]
    uv, _, valid = project_points(means.reshape(b, v * p, 3), intrinsics, extrinsics, h, w)
    scale = uv.new_tensor([2.0 / w, 2.0 / h])
    grid = torch.where(valid[..., None], uv * scale - 1.0, torch.zeros_like(uv))  # align_corners=False coords
    samples = F.grid_sample(
        images.reshape(b * v, 3, h, w), grid.reshape(b * v, 1, v * p, 2), mode="bilinear",
        padding_mode="border", align_corners=False,
    )  # [B·Vq, 3, 1, Vp·P]  # fmt: skip
    samples = samples.reshape(b, v, 3, v, p).permute(0, 3, 4, 1, 2)  # [B, Vp, P, Vq, 3]
    mask = valid.reshape(b, v, v, p).permute(0, 2, 3, 1).to(images.dtype)  # [B, Vp, P, Vq]
    idx = other_views(v, means.device)[None, :, None, :].expand(b, v, p, v - 1)  # [B, Vp, P, V-1]
    mask = torch.gather(mask, 3, idx)
    colors = torch.gather(samples, 3, idx[..., None].expand(-1, -1, -1, -1, 3)) * mask[..., None]
    return colors, mask


class ShallowMLP(nn.Module):
    """Linear, GELU, linear over the last dimension: [..., in_dim] -> [..., dim]. The GVSRE MLP (concat: over
    the descriptor of all context cameras at once; pool: per camera) and pool's warped-colour embedding."""

    def __init__(self, in_dim: int, dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(in_dim, dim), nn.GELU(), nn.Linear(dim, dim))

    def forward(self, x: Tensor) -> Tensor:
        return self.mlp(x)


class ViewDependentHead(nn.Module):
    """LayerNorm over [Gaussian-head features, GVSRE, WCM], then a 4-layer MLP (GELU after the first three,
    linear output) -> the (K - 1)·3 higher-order SH coefficients of degree ``sh_degree``."""

    def __init__(self, in_dim: int, hidden: int, sh_degree: int) -> None:
        super().__init__()
        if sh_degree < 1:
            raise ValueError("the view-dependent head predicts higher-order SH; it needs sh_degree >= 1")
        self.num_coeffs = num_sh_coeffs(sh_degree) - 1
        self.net = nn.Sequential(
            nn.LayerNorm(in_dim),
            nn.Linear(in_dim, hidden), nn.GELU(),
            nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, self.num_coeffs * 3),
        )  # fmt: skip
        nn.init.normal_(self.net[-1].weight, std=1e-3)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: Tensor) -> Tensor:
        """x [..., in_dim] -> higher-order SH [..., K - 1, 3]."""
        return self.net(x).unflatten(-1, (self.num_coeffs, 3))


class DecoupledAppearance(nn.Module, ABC):
    """Assembles every Gaussian's SH coefficients as the appearance ``mode`` (``APPEARANCE_MODES``) says.

    The Gaussian head predicts each view's SH from that view's pixels; in the baseline rows they are taken as
    they are, in view 0's frame, as NAS3R takes them (its code leaves the rotation by the view's
    camera-to-view-0 rotation out). The view-dependent head's output is taken as it is too: GVSRE feeds it
    the directions to every camera centre in that frame, so it can learn that frame's SH (``no_gvsre`` has
    no such frame cue; as in the paper, nothing turns its output either).

    A subclass per view aggregation (``VIEW_AGGREGATIONS``) builds the GVSRE and WCM inputs of the head
    (``_build_view_inputs``, ``view_inputs``); ``build_appearance`` picks it by name.
    """

    def __init__(self, mode: str, sh_degree: int, feature_dim: int, num_context_views: int = 2,
                 gvsre_dim: int = 32, hidden: int = 128) -> None:  # fmt: skip
        """num_context_views: the count a ``concat`` head is built for (``pool`` takes any)."""
        super().__init__()
        self.mode = mode
        self.parts = parts = appearance_mode(mode)
        self.sh_degree = 0 if parts.higher == "none" else sh_degree
        self.num_context_views = num_context_views
        higher = num_sh_coeffs(self.sh_degree) - 1 if parts.higher == "gaussian_head" else 0
        self.gaussian_head_sh = int(parts.dc == "gaussian_head") + higher  # the SH the Gaussian head predicts
        view_dim = self._build_view_inputs(num_context_views, gvsre_dim)
        self.view_dependent_head = (
            ViewDependentHead(feature_dim + view_dim, hidden, self.sh_degree)
            if parts.higher == "view_dependent_head"
            else None
        )

    @abstractmethod
    def _build_view_inputs(self, num_context_views: int, dim: int) -> int:
        """Create the modules that embed GVSRE / WCM (as ``parts.gvsre`` / ``parts.wcm`` ask); return the width
        they add to the view-dependent head's input."""

    @abstractmethod
    def view_inputs(self, images: Tensor, means: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        """GVSRE and WCM inputs of the view-dependent head: images [B, V, 3, H, W], means [B, V, P, 3] (view-0
        frame), intrinsics [B, V, 3, 3], extrinsics [B, V, 4, 4] of the context views -> [B, V·P, width]."""

    def check_context_views(self, count: int) -> None:
        """Refuse (UserError, one line) a number of context views this head cannot take."""

    def forward(
        self,
        images: Tensor,  # [B, V, 3, H, W] context images
        means: Tensor,  # [B, V, P, 3] Gaussian centres, view-0 frame
        features: Tensor,  # [B, V, P, F] Gaussian-head features
        head_sh: Tensor,  # [B, V, P, K', 3] SH predicted by the Gaussian head (K' >= K; the baseline modes')
        intrinsics: Tensor,  # [B, V, 3, 3] context cameras
        extrinsics: Tensor,  # [B, V, 4, 4]
    ) -> Tensor:
        """-> SH coefficients [B, V·P, K, 3]."""
        b, v, p, _ = means.shape
        blocks: list[Tensor] = [i2dc(images)] if self.parts.dc == "i2dc" else []
        if self.gaussian_head_sh:  # NAS3R's SH as the head gives them, taken in view 0's frame as they are
            k = num_sh_coeffs(self.sh_degree)
            blocks.append(head_sh[:, :, :, k - self.gaussian_head_sh : k].reshape(b, v * p, -1, 3))
        if self.view_dependent_head is not None:
            self.check_context_views(v)
            inputs = [features.reshape(b, v * p, -1), self.view_inputs(images, means, intrinsics, extrinsics)]
            blocks.append(self.view_dependent_head(torch.cat(inputs, dim=-1)))
        return torch.cat(blocks, dim=2)


class ConcatAppearance(DecoupledAppearance):
    """The paper's head: the GVSRE descriptor of all ``num_context_views`` cameras [4·C] through one MLP, and
    the warped colours and validity masks of the C - 1 other views, concatenated in view order."""

    def _build_view_inputs(self, num_context_views: int, dim: int) -> int:
        self.gvsre = ShallowMLP(4 * num_context_views, dim) if self.parts.gvsre else None
        wcm_dim = 4 * (num_context_views - 1)  # colour + mask per other context view
        return (dim if self.parts.gvsre else 0) + (wcm_dim if self.parts.wcm else 0)

    def check_context_views(self, count: int) -> None:
        if self.view_dependent_head is not None and count != self.num_context_views:
            raise UserError(
                f"the paper's appearance head (model.net.view_aggregation: concat) is built for "
                f"{self.num_context_views} context views and got {count}; set model.net.view_aggregation: pool "
                "for one head that takes any number of views"
            )

    def view_inputs(self, images: Tensor, means: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        b, v, p, _ = means.shape
        inputs = []
        if self.gvsre is not None:
            inputs.append(self.gvsre(gvsre_descriptor(means.reshape(b, v * p, 3), extrinsics[:, :, :3, 3])))
        if self.parts.wcm:
            colors, mask = warped_color_map(means, images, intrinsics, extrinsics)
            inputs += [colors.reshape(b, v * p, -1), mask.reshape(b, v * p, -1)]
        return torch.cat(inputs, dim=-1)


class PooledAppearance(DecoupledAppearance):
    """One head for any number of context views (beyond the paper; docs/design.md):

    - GVSRE: each camera's relation [direction (3), log distance, 1 for the Gaussian's own view] through one
      MLP, averaged over all context cameras -> [dim];
    - WCM: each other view's [warped colour (3), the Gaussian's own pixel colour (3), and with GVSRE that
      view's relation (4)] through a second MLP, averaged over the views that see the Gaussian (validity
      mask), plus whether any does -> [dim + 1]. A view that does not see the Gaussian takes no part.

    Means are symmetric in their arguments, so permuting the non-reference context views permutes the
    Gaussians and changes nothing else.
    """

    def _build_view_inputs(self, num_context_views: int, dim: int) -> int:
        self.gvsre = ShallowMLP(5, dim) if self.parts.gvsre else None
        self.wcm = ShallowMLP(6 + (4 if self.parts.gvsre else 0), dim) if self.parts.wcm else None
        return (dim if self.parts.gvsre else 0) + (dim + 1 if self.parts.wcm else 0)

    def view_inputs(self, images: Tensor, means: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        b, v, p, _ = means.shape
        relation = gvsre_descriptor(means.reshape(b, v * p, 3), extrinsics[:, :, :3, 3])
        relation = relation.reshape(b, v, p, v, 4)  # [B, Vp, P, Vc, 4]
        inputs = []
        if self.gvsre is not None:
            own = torch.eye(v, dtype=means.dtype, device=means.device)[
                None, :, None, :, None
            ]  # [1, Vp, 1, Vc, 1]
            own = own.expand(b, v, p, v, 1)
            inputs.append(self.gvsre(torch.cat([relation, own], dim=-1)).mean(-2).reshape(b, v * p, -1))
        if self.wcm is not None:
            colors, mask = warped_color_map(means, images, intrinsics, extrinsics)  # [B, V, P, V-1, 3 | -]
            pixel = images.permute(0, 1, 3, 4, 2).reshape(b, v, p, 1, 3).expand(-1, -1, -1, v - 1, -1)
            seen_from = [colors, pixel]
            if self.gvsre is not None:
                idx = other_views(v, means.device)[None, :, None, :, None].expand(b, v, p, v - 1, 4)
                seen_from.append(torch.gather(relation, 3, idx))  # [B, V, P, V-1, 4]: the other views' relation
            pooled = masked_mean(self.wcm(torch.cat(seen_from, dim=-1)), mask)  # [B, V, P, dim]
            seen = mask.amax(-1, keepdim=True)  # [B, V, P, 1]: 1 if any other view sees the Gaussian
            inputs += [pooled.reshape(b, v * p, -1), seen.reshape(b, v * p, 1)]
        return torch.cat(inputs, dim=-1)


VIEW_AGGREGATIONS: dict[str, type[DecoupledAppearance]] = {"concat": ConcatAppearance, "pool": PooledAppearance}


def build_appearance(aggregation: str, mode: str, sh_degree: int, feature_dim: int, num_context_views: int = 2,
                     gvsre_dim: int = 32, hidden: int = 128) -> DecoupledAppearance:  # fmt: skip
    """The appearance module of ``aggregation`` (a key of ``VIEW_AGGREGATIONS``); arguments as
    :class:`DecoupledAppearance`."""
    if aggregation not in VIEW_AGGREGATIONS:
        choices = ", ".join(VIEW_AGGREGATIONS)
        raise ValueError(f"unknown view aggregation {aggregation!r}; choose one of {choices}")
    return VIEW_AGGREGATIONS[aggregation](mode, sh_degree, feature_dim, num_context_views, gvsre_dim, hidden)
