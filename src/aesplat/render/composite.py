"""Front-to-back alpha compositing of tile lists, with a hand-written backward.

Each tile's list is walked in chunks of ``chunk`` Gaussians for all still-active tiles at once
([tiles, pixels, chunk] blocks); transmittance is carried multiplicatively between chunks. A tile leaves
the active set as soon as every one of its pixels has stopped (transmittance would fall below 1e-4) or its
list is exhausted, so saturated tiles cost nothing more. The backward walks the same chunks back to front,
recomputing alphas from the saved chunk-entry transmittance instead of keeping an autograd graph.

Per pixel and Gaussian i (gsplat "classic"): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,
alpha = min(0.99, o exp(-sigma)), skipped when alpha < 1/255 or sigma < 0; the walk stops before the
Gaussian that would bring the transmittance to 1e-4 or below.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import ALPHA_MIN
from .tiles import TileBins

ALPHA_MAX = 0.99
T_MIN = 1e-4
_PACK = 10  # packed per-Gaussian row: mean x, y | conic a, b, c | opacity | r, g, b | depth


def _tile_pixels(
    tiles: Tensor, bins: TileBins, height: int, width: int, dtype: torch.dtype
) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel-centre coordinates px, py [G, P] of the given tiles, and a mask [G, P] of pixels off the image."""
    ts = bins.tile_size
    local = torch.arange(ts * ts, device=tiles.device)
    rem = tiles % (bins.tiles_x * bins.tiles_y)
    ty, tx = rem // bins.tiles_x, rem % bins.tiles_x
    xi = tx[:, None] * ts + local % ts
    yi = ty[:, None] * ts + local // ts
    return xi.to(dtype) + 0.5, yi.to(dtype) + 0.5, (xi >= width) | (yi >= height)


def _alphas(p: Tensor, px: Tensor, py: Tensor):
    """Alpha of each chunk Gaussian at each pixel. p [a, C, 10] packed rows, px, py [a, P] -> [a, P, C] each."""
    dx = p[:, None, :, 0] - px[:, :, None]
    dy = p[:, None, :, 1] - py[:, :, None]
    ca, cb, cc = p[:, None, :, 2], p[:, None, :, 3], p[:, None, :, 4]
    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    gauss = torch.exp(-sigma)
    raw = p[:, None, :, 5] * gauss
    alpha = raw.clamp_max(ALPHA_MAX)
    used = (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    return dx, dy, gauss, raw, alpha, used


def _transmittance(alpha: Tensor, t0: Tensor, done0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Inclusive products [a, P, C], the transmittance before each Gaussian, and which ones are composited."""
    prod = t0[..., None] * torch.cumprod(1.0 - alpha, dim=-1)
    before = torch.cat([t0[..., None], prod[..., :-1]], dim=-1)
    incl = (prod > T_MIN) & ~done0[..., None]
    return prod, before, incl


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, packed: Tensor, bins: TileBins, height: int, width: int, chunk: int, max_elements: int):
        npix = bins.tile_size**2
        nt = bins.num_tiles
        rgb = packed.new_zeros(nt, npix, 3)
        depth = packed.new_zeros(nt, npix)
        trans = packed.new_ones(nt, npix)
        counts = bins.counts
        tiles = torch.sort(counts, descending=True, stable=True).indices
        tiles = tiles[: int((counts > 0).sum())]  # non-empty tiles, longest list first
        group = max(1, max_elements // (npix * chunk))
        saved = []
        for g0 in range(0, tiles.numel(), group):
            t = tiles[g0 : g0 + group]
            steps = _forward_group(packed, bins, t, height, width, chunk, rgb, depth, trans)
            saved.append((t, steps))
        ctx.bins, ctx.saved, ctx.hw, ctx.chunk = bins, saved, (height, width), chunk
        ctx.save_for_backward(packed, trans)
        return rgb, depth, trans

    @staticmethod
    def backward(ctx, g_rgb: Tensor, g_depth: Tensor, g_trans: Tensor):
        packed, trans = ctx.saved_tensors
        grad = torch.zeros_like(packed)
        g_rgb = torch.zeros_like(trans)[..., None].expand(-1, -1, 3) if g_rgb is None else g_rgb
        g_depth = torch.zeros_like(trans) if g_depth is None else g_depth
        g_trans = torch.zeros_like(trans) if g_trans is None else g_trans
        h, w = ctx.hw
        for t, steps in ctx.saved:
            _backward_group(packed, ctx.bins, t, h, w, ctx.chunk, steps, g_rgb, g_depth, g_trans, trans, grad)
        return grad, None, None, None, None, None


def _gather_chunk(
    packed: Tensor, bins: TileBins, starts: Tensor, counts: Tensor, k0: int, chunk: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Packed rows [a, C, 10] of list positions k0 .. k0 + C of the given tiles; padding rows have opacity 0."""
    pos = k0 + torch.arange(chunk, device=packed.device)
    valid = pos[None] < counts[:, None]  # [a, C]
    idx = (starts[:, None] + pos[None]).clamp_max(bins.order.numel() - 1)
    gid = torch.where(valid, bins.order[idx], torch.zeros_like(idx))
    p = packed[gid]
    p[..., 5] = torch.where(valid, p[..., 5], torch.zeros_like(p[..., 5]))
    return p, gid, valid


def _forward_group(packed, bins, tiles, height, width, chunk, rgb, depth, trans):
    """Composite one group of tiles in place; returns per-chunk (active local ids, entry T, entry done)."""
    px, py, off = _tile_pixels(tiles, bins, height, width, packed.dtype)
    starts, counts = bins.starts[tiles], bins.counts[tiles]
    t_loc = packed.new_ones(tiles.numel(), px.shape[1])
    done = off.clone()  # pixels off the image never need compositing
    c_loc = packed.new_zeros(tiles.numel(), px.shape[1], 3)
    d_loc = packed.new_zeros(tiles.numel(), px.shape[1])
    act = torch.arange(tiles.numel(), device=packed.device)
    steps = []
    k0 = 0
    while act.numel() > 0:
        p, _, _ = _gather_chunk(packed, bins, starts[act], counts[act], k0, chunk)
        t0, done0 = t_loc[act], done[act]
        steps.append((act, t0, done0))
        _, _, _, _, alpha, _ = _alphas(p, px[act], py[act])
        prod, before, incl = _transmittance(alpha, t0, done0)
        wgt = torch.where(incl, alpha * before, torch.zeros_like(alpha))  # [a, P, C]
        c_loc[act] += torch.bmm(wgt, p[..., 6:9])
        d_loc[act] += torch.bmm(wgt, p[..., 9:10])[..., 0]
        t_loc[act] = torch.where(incl, prod, t0[..., None]).amin(-1)
        done[act] = done0 | (prod[..., -1] <= T_MIN)
        k0 += chunk
        alive = (counts[act] > k0) & ~done[act].all(-1)
        act = act[alive]
    rgb[tiles], depth[tiles], trans[tiles] = c_loc, d_loc, t_loc
    return steps


def _backward_group(packed, bins, tiles, height, width, chunk, steps, g_rgb, g_depth, g_trans, trans, grad):
    """Accumulate d loss / d packed rows for one group of tiles into ``grad`` [M, 10]."""
    px, py, _ = _tile_pixels(tiles, bins, height, width, packed.dtype)
    starts, counts = bins.starts[tiles], bins.counts[tiles]
    gc_all, gd_all = g_rgb[tiles], g_depth[tiles]
    # d L / d alpha_i through the final transmittance: -g_T * T_final / (1 - alpha_i); folded into the suffix.
    suffix = g_trans[tiles] * trans[tiles]  # [G, P]: sum_{j>i} w_j g_j + g_T T_final, built back to front
    for k in range(len(steps) - 1, -1, -1):
        act, t0, done0 = steps[k]
        p, gid, valid = _gather_chunk(packed, bins, starts[act], counts[act], k * chunk, chunk)
        dx, dy, gauss, raw, alpha, used = _alphas(p, px[act], py[act])
        _, before, incl = _transmittance(alpha, t0, done0)
        wgt = torch.where(incl, alpha * before, torch.zeros_like(alpha))  # [a, P, C]
        gc, gd = gc_all[act], gd_all[act]  # [a, P, 3], [a, P]
        gi = torch.bmm(gc, p[..., 6:9].transpose(1, 2)) + gd[..., None] * p[:, None, :, 9]  # [a, P, C]
        wg = wgt * gi
        after = suffix[act][..., None] + (wg.flip(-1).cumsum(-1).flip(-1) - wg)  # sum over later j
        suffix[act] = suffix[act] + wg.sum(-1)
        d_alpha = before * gi - after / (1.0 - alpha)
        d_alpha = torch.where(incl & used & (raw < ALPHA_MAX), d_alpha, torch.zeros_like(d_alpha))
        d_sigma = -d_alpha * alpha
        ca, cb, cc = p[:, None, :, 2], p[:, None, :, 3], p[:, None, :, 4]
        g = torch.stack(
            [
                (d_sigma * (ca * dx + cb * dy)).sum(1),
                (d_sigma * (cb * dx + cc * dy)).sum(1),
                0.5 * (d_sigma * dx * dx).sum(1),
                (d_sigma * dx * dy).sum(1),
                0.5 * (d_sigma * dy * dy).sum(1),
                (d_alpha * gauss).sum(1),
            ],
            dim=-1,
        )  # [a, C, 6]
        g_col = torch.bmm(wgt.transpose(1, 2), gc)  # [a, C, 3]
        g_z = torch.bmm(wgt.transpose(1, 2), gd[..., None])  # [a, C, 1]
        rows = torch.cat([g, g_col, g_z], dim=-1) * valid[..., None]
        grad.index_add_(0, gid.reshape(-1), rows.reshape(-1, _PACK))


def composite(
    means2d: Tensor,  # [M, 2]
    conics: Tensor,  # [M, 3]
    opacities: Tensor,  # [M]
    colors: Tensor,  # [M, 3]
    depths: Tensor,  # [M]
    bins: TileBins,
    height: int,
    width: int,
    chunk: int = 32,
    max_elements: int = 1 << 22,
    compiled: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite the binned Gaussians into images.

    Returns colour [C, 3, H, W] (no background), depth numerator sum_i w_i z_i [C, 1, H, W] and final
    transmittance [C, 1, H, W] for the C = ``bins.num_cameras`` cameras. ``max_elements`` bounds the
    [tiles, pixels, chunk] blocks (memory scales with it); ``chunk`` is the list step.
    """
    packed = torch.cat([means2d, conics, opacities[:, None], colors, depths[:, None]], dim=-1)
    rgb, depth, trans = _Composite.apply(packed, bins, height, width, chunk, max_elements)
    return (
        _untile(rgb, bins, height, width),
        _untile(depth[..., None], bins, height, width),
        _untile(trans[..., None], bins, height, width),
    )


def _untile(x: Tensor, bins: TileBins, height: int, width: int) -> Tensor:
    """[tiles, P, D] in tile order -> [C, D, H, W] cropped to the image."""
    ts, d = bins.tile_size, x.shape[-1]
    x = x.reshape(bins.num_cameras, bins.tiles_y, bins.tiles_x, ts, ts, d)
    x = x.permute(0, 5, 1, 3, 2, 4).reshape(bins.num_cameras, d, bins.tiles_y * ts, bins.tiles_x * ts)
    return x[:, :, :height, :width]
