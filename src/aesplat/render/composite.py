"""Front-to-back alpha compositing of tile lists, with a hand-written backward.

Each tile's list is walked in chunks of ``chunk`` Gaussians for all still-active tiles at once
([tiles, pixels, chunk] blocks); transmittance is carried multiplicatively between chunks. A tile leaves
the active set as soon as every one of its pixels has stopped (transmittance would fall below 1e-4) or its
list is exhausted, so saturated tiles cost nothing more. The backward walks the same chunks back to front,
recomputing alphas from the saved chunk-entry transmittance instead of keeping an autograd graph.

The walk is sequential along the lists, so a few tiles with long lists (a small image, or the last tiles of
a large one) would cost one Python-dispatched step per ``chunk`` Gaussians whatever the pixel count. When
the active tiles are few, a step therefore takes more of each list: at least ``step_elements`` elements per
step (``chunk`` times a power of two, within ``max_elements``). The result is the same up to float rounding
(the carry between steps sits at other list positions); the cost then follows the elements, not the lists.

Per pixel and Gaussian i (gsplat "classic"): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,
alpha = min(0.99, o exp(-sigma)), skipped when alpha < 1/255 or sigma < 0; the walk stops before the
Gaussian that would bring the transmittance to 1e-4 or below.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .projection import ALPHA_MIN
from .tiles import TileBins

ALPHA_MAX = 0.99
T_MIN = 1e-4
_PACK = 10  # packed per-Gaussian row: mean x, y | conic a, b, c | opacity | r, g, b | depth


def _pixel_monomials(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[6, P] rows 1, u, v, u^2, u v, v^2 of pixel centres relative to the tile centre (same for all tiles)."""
    local = torch.arange(tile_size * tile_size, device=device)
    u = (local % tile_size).to(dtype) + 0.5 - tile_size / 2
    v = (local // tile_size).to(dtype) + 0.5 - tile_size / 2
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v])


def _tile_geometry(tiles: Tensor, bins: TileBins, height: int, width: int, dtype: torch.dtype):
    """Tile centres [G, 2] in pixels, and a mask [G, P] of pixels that fall off the image."""
    ts = bins.tile_size
    rem = tiles % (bins.tiles_x * bins.tiles_y)
    ty, tx = rem // bins.tiles_x, rem % bins.tiles_x
    centre = torch.stack([tx, ty], -1).to(dtype) * ts + ts / 2
    local = torch.arange(ts * ts, device=tiles.device)
    off = (tx[:, None] * ts + local % ts >= width) | (ty[:, None] * ts + local // ts >= height)
    return centre, off


def _gather_chunk(
    packed: Tensor, bins: TileBins, starts: Tensor, counts: Tensor, k0: int, chunk: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Packed rows [a, C, 10] of list positions k0 .. k0 + C of the given tiles, their ids and validity."""
    pos = k0 + torch.arange(chunk, device=packed.device)
    valid = pos[None] < counts[:, None]  # [a, C]
    idx = (starts[:, None] + pos[None]).clamp_max(bins.order.numel() - 1)
    gid = torch.where(valid, bins.order.index_select(0, idx.reshape(-1)).view_as(idx), 0)
    return packed.index_select(0, gid.reshape(-1)).view(*gid.shape, _PACK), gid, valid


def _exponent(p: Tensor, centre: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Coefficients [a, C, 6] with log(o) - sigma = coeffs @ monomials, and tile-relative means [a, C, 2].

    sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 with dx = m - pixel is expanded in the pixel's offset from the
    tile centre, so one small matmul gives the exponent for every (Gaussian, pixel) pair.
    """
    m = p[..., 0:2] - centre[:, None]  # [a, C, 2]
    mx, my = m.unbind(-1)
    a, b, c = p[..., 2], p[..., 3], p[..., 4]
    f = 0.5 * a * mx * mx + b * mx * my + 0.5 * c * my * my
    log_o = torch.where(valid, torch.log(p[..., 5].clamp_min(1e-30)), torch.full_like(f, -1e4))
    coeffs = torch.stack([log_o - f, a * mx + b * my, b * mx + c * my, -0.5 * a, -b, -0.5 * c], dim=-1)
    return coeffs, m


def _alphas(coeffs: Tensor, mono: Tensor) -> Tensor:
    """Composited alphas [a, C, P]: o exp(-sigma) clamped to 0.99, and exactly 0 below 1/255.

    Three in-place passes over one buffer. ``threshold_`` keeps x > t, so t is the largest value of the
    working dtype below 1/255: the kept set is exactly x >= 1/255.
    """
    alpha = torch.exp_(coeffs @ mono)
    torch.nn.functional.threshold_(alpha, _alpha_floor(alpha.dtype), 0.0)
    return alpha.clamp_max_(ALPHA_MAX)


_FLOORS: dict[torch.dtype, float] = {}


def _alpha_floor(dtype: torch.dtype) -> float:
    """The largest ``dtype`` value below ALPHA_MIN (as ALPHA_MIN itself rounds in that dtype)."""
    if dtype not in _FLOORS:
        one = torch.tensor(ALPHA_MIN, dtype=dtype)
        _FLOORS[dtype] = float(torch.nextafter(one, torch.zeros_like(one)))
    return _FLOORS[dtype]


def _transmittance(alpha: Tensor, t0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Transmittance before and after each Gaussian [a, C, P] (two views of one buffer), and the
    inclusion mask: the walk stops before a Gaussian that would bring T to 1e-4 or below.

    ``t0`` [a, P] is the transmittance entering the chunk, 0 for pixels that have already stopped. T is
    non-increasing along the list, so each pixel's included Gaussians are a prefix.
    """
    if torch.compiler.is_compiling():  # inductor fuses this form; the in-place one below is for eager
        buf = torch.cumprod(torch.cat([t0[:, None], 1.0 - alpha], dim=1), dim=1)
    else:
        a, c, p = alpha.shape
        buf = alpha.new_empty(a, c + 1, p)
        buf[:, 0] = t0
        torch.sub(alpha.new_ones(()), alpha, out=buf[:, 1:])  # 1 - alpha, written in place
        buf.cumprod_(1)
    t_after = buf[:, 1:]
    return buf[:, :-1], t_after, t_after > T_MIN


def _forward_chunk(p: Tensor, centre: Tensor, valid: Tensor, t0: Tensor, mono: Tensor):
    """One compositing step for a tiles: colour+depth sums [a, 4, P], transmittance after the step [a, P]
    and which pixels stopped in it [a, P] (t0 is 0 for pixels that had stopped before)."""
    coeffs, _ = _exponent(p, centre, valid)
    alpha = _alphas(coeffs, mono)
    t_before, t_after, incl = _transmittance(alpha, t0)
    wgt = alpha.mul_(t_before).mul_(incl)  # alpha_i T_i where included
    f_add = p[..., 6:10].transpose(1, 2) @ wgt
    if torch.compiler.is_compiling():
        t_new = torch.where(incl, t_after, t0[:, None]).amin(1)
    else:  # the last included T, found from the prefix length: no pass over the whole block
        last = incl.sum(1, keepdim=True)
        t_new = torch.where(last[:, 0] > 0, t_after.gather(1, (last - 1).clamp_min_(0))[:, 0], t0)
    return f_add, t_new, t_after[:, -1] <= T_MIN


def _backward_chunk(
    p: Tensor, centre: Tensor, valid: Tensor, t0: Tensor, mono: Tensor, gf: Tensor, suffix: Tensor
):
    """Gradient rows [a, C, 10] of one step, and the suffix sum [a, P] entering the previous step.

    gf [a, 4, P] is d loss / d (colour, depth sums); suffix [a, P] is sum over later Gaussians of
    w_j d loss / d w_j plus g_T T_final.
    """
    coeffs, m = _exponent(p, centre, valid)
    alpha = _alphas(coeffs, mono)
    t_before, t_after, incl = _transmittance(alpha, t0)
    wgt = (alpha * t_before).mul_(incl)
    g_feat = wgt @ gf.transpose(1, 2)  # d loss / d (colour, depth) of each Gaussian
    gi = p[..., 6:10] @ gf  # [a, C, P]: d L / d w_i per pixel
    wg = wgt.mul_(gi)
    total = suffix + wg.sum(1)
    after = wg.cumsum_(1).neg_().add_(total[:, None])  # sum over j > i
    # (1 - alpha_i) d L / d alpha_i = g_i T_after_i - after_i. Clamped alphas (0.99) pass no gradient, and
    # skipped ones (alpha = 0) none either: q = alpha d L / d alpha = -d L / d sigma vanishes there.
    # Masks are applied by multiplication: torch.where is many times slower than a multiply on the CPU.
    free = incl.logical_and_(alpha < ALPHA_MAX)
    odds = alpha.div_(1.0 - alpha).mul_(free)  # alpha / (1 - alpha) <= 99
    q = gi.mul_(t_after).sub_(after).mul_(odds)
    # d loss / d sigma = -q; the pixel sums below are polynomial moments of q (one small matmul).
    s0, su, sv, suu, suv, svv = (q @ mono.transpose(0, 1)).unbind(-1)
    mx, my = m.unbind(-1)
    a, b, c = p[..., 2], p[..., 3], p[..., 4]
    sdx, sdy = mx * s0 - su, my * s0 - sv  # sum q dx, sum q dy
    sdxx = mx * mx * s0 - 2 * mx * su + suu
    sdxy = mx * my * s0 - mx * sv - my * su + suv
    sdyy = my * my * s0 - 2 * my * sv + svv
    g_opacity = s0 / p[..., 5].clamp_min(1e-30)
    g_geo = torch.stack(
        [-(a * sdx + b * sdy), -(b * sdx + c * sdy), -0.5 * sdxx, -sdxy, -0.5 * sdyy, g_opacity], -1
    )
    rows = torch.cat([g_geo, g_feat], dim=-1) * valid[..., None]
    return rows, total


_COMPILED: dict[str, Callable] = {}


def _chunk_functions(compiled: bool) -> tuple[Callable, Callable]:
    """The per-step kernels, eager or through ``torch.compile`` (compiled once per process, then cached)."""
    if not compiled:
        return _forward_chunk, _backward_chunk
    if not _COMPILED:
        _COMPILED["forward"] = torch.compile(_forward_chunk, dynamic=True)
        _COMPILED["backward"] = torch.compile(_backward_chunk, dynamic=True)
    return _COMPILED["forward"], _COMPILED["backward"]


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        packed: Tensor,
        bins: TileBins,
        height: int,
        width: int,
        chunk: int,
        max_elements: int,
        compiled: bool,
        step_elements: int,
    ):
        fwd, bwd = _chunk_functions(compiled)
        npix = bins.tile_size**2
        nt = bins.num_tiles
        feat = packed.new_zeros(nt, 4, npix)  # r, g, b, depth sums
        trans = packed.new_ones(nt, npix)
        counts = bins.counts
        tiles = torch.sort(counts, descending=True, stable=True).indices
        tiles = tiles[: int((counts > 0).sum())]  # non-empty tiles, longest list first
        group = max(1, max_elements // (npix * chunk))
        mono = _pixel_monomials(bins.tile_size, packed.dtype, packed.device)
        steps = _StepSizes(chunk, npix, step_elements, max_elements)
        saved = []
        for g0 in range(0, tiles.numel(), group):
            t = tiles[g0 : g0 + group]
            saved.append((t, _forward_group(fwd, packed, bins, t, height, width, steps, mono, feat, trans)))
        ctx.bins, ctx.saved, ctx.hw, ctx.bwd = bins, saved, (height, width), bwd
        ctx.save_for_backward(packed, trans)
        return feat, trans

    @staticmethod
    def backward(ctx, g_feat: Tensor | None, g_trans: Tensor | None):
        packed, trans = ctx.saved_tensors
        grad = torch.zeros_like(packed)
        g_feat = torch.zeros(trans.shape[0], 4, trans.shape[1]).to(trans) if g_feat is None else g_feat
        g_trans = torch.zeros_like(trans) if g_trans is None else g_trans
        mono = _pixel_monomials(ctx.bins.tile_size, packed.dtype, packed.device)
        h, w = ctx.hw
        for t, steps in ctx.saved:
            _backward_group(ctx.bwd, packed, ctx.bins, t, h, w, mono, steps, g_feat, g_trans, trans, grad)
        return grad, None, None, None, None, None, None, None


class _StepSizes:
    """How many Gaussians of each list one compositing step takes: ``chunk``, doubled while the active tiles
    are so few that a step would hold fewer than ``step_elements`` elements (and the block stays within
    ``max_elements``), never more than the longest remaining list needs."""

    def __init__(self, chunk: int, npix: int, step_elements: int, max_elements: int) -> None:
        self.chunk, self.npix, self.step_elements, self.max_elements = chunk, npix, step_elements, max_elements

    def __call__(self, tiles: int, remaining: int) -> int:
        step = self.chunk
        while (
            tiles * self.npix * step < self.step_elements
            and step < remaining
            and tiles * self.npix * step * 2 <= self.max_elements
        ):
            step *= 2
        return step


def _forward_group(fwd, packed, bins, tiles, height, width, step_sizes, mono, feat, trans):
    """Composite one group of tiles into ``feat`` / ``trans``; returns per step (active ids, entry T, list
    position, step length)."""
    centre, off = _tile_geometry(tiles, bins, height, width, packed.dtype)
    starts, counts = bins.starts[tiles], bins.counts[tiles]
    longest = counts.tolist()  # tiles come longest list first: the first active tile has the longest
    t_loc = packed.new_ones(tiles.numel(), mono.shape[1])
    live = (~off).to(packed.dtype)  # 0 once a pixel has stopped (and for pixels off the image)
    f_loc = packed.new_zeros(tiles.numel(), 4, mono.shape[1])
    act: slice | Tensor = slice(0, tiles.numel())
    steps = []
    k0 = 0
    while (n_act := _count(act)) > 0:
        first = 0 if isinstance(act, slice) else int(act[0])
        step = step_sizes(n_act, longest[first] - k0)
        p, _, valid = _gather_chunk(packed, bins, starts[act], counts[act], k0, step)
        live_act = live[act]
        t0 = t_loc[act] * live_act
        steps.append((act, t0, k0, step))
        f_add, t_new, stopped = fwd(p, centre[act], valid, t0, mono)
        f_loc[act] += f_add
        t_loc[act] = torch.where(live_act > 0, t_new, t_loc[act])
        live_act = torch.where(stopped, torch.zeros_like(live_act), live_act)
        live[act] = live_act
        k0 += step
        act = _next_active(act, (counts[act] > k0) & (live_act > 0).any(-1), tiles.numel())
    feat[tiles], trans[tiles] = f_loc, t_loc
    return steps


def _count(act: slice | Tensor) -> int:
    return act.stop if isinstance(act, slice) else act.numel()


def _next_active(act: slice | Tensor, alive: Tensor, n: int) -> slice | Tensor:
    """The tiles still active: a slice while they form a prefix (tiles are sorted by list length, so they do
    until some tile saturates), which makes every per-tile read and write a view instead of a copy."""
    n_alive = int(alive.sum())
    if isinstance(act, slice) and bool(alive[:n_alive].all()):
        return slice(0, n_alive)
    idx = torch.arange(n, device=alive.device)[act] if isinstance(act, slice) else act
    return idx[alive]


def _backward_group(bwd, packed, bins, tiles, height, width, mono, steps, g_feat, g_trans, trans, grad):
    """Accumulate d loss / d packed rows for one group of tiles into ``grad`` [M, 10]."""
    centre, _ = _tile_geometry(tiles, bins, height, width, packed.dtype)
    starts, counts = bins.starts[tiles], bins.counts[tiles]
    gf_all = g_feat[tiles]  # [G, 4, P]
    # Through T_final, d L / d alpha_i gets -g_T T_final / (1 - alpha_i): it joins the suffix sum below.
    suffix = g_trans[tiles] * trans[tiles]  # [G, P]: sum over later j of w_j g_j, plus g_T T_final
    for k in range(len(steps) - 1, -1, -1):
        act, t0, k0, step = steps[k]
        p, gid, valid = _gather_chunk(packed, bins, starts[act], counts[act], k0, step)
        rows, suffix[act] = bwd(p, centre[act], valid, t0, mono, gf_all[act], suffix[act])
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
    step_elements: int = 1 << 16,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite the binned Gaussians into images.

    Returns colour [C, 3, H, W] (no background), depth numerator sum_i w_i z_i [C, 1, H, W] and final
    transmittance [C, 1, H, W] for the C = ``bins.num_cameras`` cameras. ``max_elements`` bounds the
    [tiles, pixels, chunk] blocks (memory scales with it); ``chunk`` is the list step, grown while fewer
    than ``step_elements`` elements would make a step (0: always ``chunk``).
    """
    packed = torch.cat([means2d, conics, opacities[:, None], colors, depths[:, None]], dim=-1)
    feat, trans = _Composite.apply(packed, bins, height, width, chunk, max_elements, compiled, step_elements)
    feat = _untile(feat, bins, height, width)
    return feat[:, :3], feat[:, 3:], _untile(trans[:, None], bins, height, width)


def _untile(x: Tensor, bins: TileBins, height: int, width: int) -> Tensor:
    """[tiles, D, P] in tile order -> [C, D, H, W] cropped to the image."""
    ts, d = bins.tile_size, x.shape[1]
    x = x.reshape(bins.num_cameras, bins.tiles_y, bins.tiles_x, d, ts, ts)
    x = x.permute(0, 3, 1, 4, 2, 5).reshape(bins.num_cameras, d, bins.tiles_y * ts, bins.tiles_x * ts)
    return x[:, :, :height, :width]
