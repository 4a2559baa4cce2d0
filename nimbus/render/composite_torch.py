"""Per-tile front-to-back alpha compositing in vectorised torch, with a hand-written backward.

This is the compositing stage of the rasterizer; ``nimbus.kernels.raster.composite``
is a drop-in replacement with the same signature and rules.

Rules (shared with the C++ kernel and :mod:`nimbus.render.reference`)
--------------------------------------------------------------------
For a pixel centre p and the Gaussians of its tile in front-to-back order:

* ``d = p - mean``, ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``,
  ``alpha = min(ALPHA_MAX, opacity * exp(-sigma))``;
* a Gaussian is skipped when ``sigma < 0`` or ``alpha < ALPHA_MIN``;
* the pixel stops *before* the first Gaussian for which ``T (1 - alpha) < T_STOP``
  (that Gaussian is excluded);
* ``rgb = sum c_i alpha_i T_i + T_final * background``, ``depth = sum z_i alpha_i T_i``
  (not normalised), ``alpha = 1 - T_final``.

How it is fast in torch
-----------------------
* Exact culling: each tile is split into sub-tiles (``CompositeConfig.subtile``) and a
  Gaussian is dropped from a sub-tile when the ellipse where its alpha reaches
  ALPHA_MIN (``sigma <= ln(255 opacity)``) misses the sub-tile's pixel centres.  Such a
  Gaussian would be skipped at every pixel there, so results are unchanged (the test
  is conservative by a small margin); only work is saved.
* Non-empty sub-tiles are sorted by list length and processed in batches of L: their
  Gaussians are gathered into a padded [L, K_chunk] block and evaluated against the
  L x P pixels as one dense [L, P, K_chunk] tensor.  The exponent ``ln(opacity) - sigma``
  is a quadratic in the pixel coordinates, so it is one batched matrix product of the
  pixel monomials (1, x, y, x^2, xy, y^2) [P, 6] with per-Gaussian coefficients [6, K].
* Transmittance is a cumulative product, carried across chunks.  The stop rule is a
  mask on the inclusive product (it is non-increasing, so ``product >= T_STOP`` selects
  exactly the Gaussians before the stop).  Sub-tiles whose pixels have all stopped, or
  whose lists are exhausted, leave the batch.  Memory is bounded by
  ``CompositeConfig.batch_elements``.
* Masks are float multiplications, never ``torch.where`` on the big tensors (the CPU
  ``where`` kernel branches per element and is ~20x slower on random masks).

The backward does not keep the forward's intermediate tensors: it replays the same
chunks (the same arithmetic, so the same stop decisions) and applies the analytic
gradient.  With ``f_i = g_rgb . c_i + g_depth z_i`` and ``w_i = alpha_i T_i``,

    dL/dalpha_i = f_i T_i - (R - sum_{j<=i} f_j w_j) / (1 - alpha_i),
    R = g_rgb . rgb + g_depth depth - g_alpha T_final,

so the suffix sum that a back-to-front walk would need is obtained from the saved
outputs and a forward prefix sum, and chunks can be replayed in forward order.  The
gradient of the exponent's six coefficients is again one batched product with the
pixel monomials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from nimbus.render.binning import tile_grid

ALPHA_MAX = 0.99
"""Upper clamp of a Gaussian's alpha (gsplat HEAD and Inria 3DGS)."""
ALPHA_MIN = 1.0 / 255.0
"""Gaussians with a smaller alpha at a pixel are skipped there."""
T_STOP = 1e-4
"""A pixel stops before a Gaussian that would bring its transmittance below this."""


@dataclass(frozen=True)
class CompositeConfig:
    """Work-size knobs of the torch compositor (results do not depend on them).

    Attributes
    ----------
    subtile : int
        Side of the sub-tiles the tiles are split into for culling and compositing
        (pixels); used when it divides the tile size, else the tile itself is used.
    chunk : int
        Gaussians per sub-tile evaluated per step (the K of the [L, P, K] block).
    batch_elements : int
        Upper bound on L * P * K, the elements of one dense block; about ten such
        float tensors are alive at once, so 2**19 elements is about 20 MB in float32.
    """

    subtile: int = 8
    chunk: int = 64
    batch_elements: int = 1 << 19

    def block_bytes(self, tile_size: int) -> float:
        """About how many bytes the largest dense block takes at ``tile_size``: ten float32 tensors of its
        elements; a (sub-)tile whose ``pixels x chunk`` alone exceeds ``batch_elements`` is a block by itself."""
        sub = _subtile_size(tile_size, self)
        return max(self.batch_elements, float(sub) * sub * self.chunk) * 10 * 4


def composite(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    isect_ids: Tensor,
    tile_offsets: Tensor,
    width: int,
    height: int,
    tile_size: int,
    background: Tensor,
    *,
    config: CompositeConfig | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite M projected Gaussians into an image (see the module docstring for the rules).

    Parameters
    ----------
    means2d : Tensor [M, 2]      pixel coordinates, pixel-corner origin.
    conics : Tensor [M, 3]       (a, b, c) of the inverse 2D covariance.
    colors : Tensor [M, 3]       RGB.
    opacities : Tensor [M]       in (0, 1) (already activated).
    depths : Tensor [M]          camera z.
    isect_ids : Tensor [I] int64     Gaussian indices grouped by tile, front to back per tile.
    tile_offsets : Tensor [T+1] int64  tile t owns ``isect_ids[tile_offsets[t]:tile_offsets[t+1]]``,
        tiles row-major, ``T = ceil(W / tile_size) * ceil(H / tile_size)``.
    width, height, tile_size : int
    background : Tensor [3]      colour behind everything.
    config : CompositeConfig, optional

    Returns
    -------
    rgb : Tensor [H, W, 3]
    depth : Tensor [H, W]        ``sum z_i alpha_i T_i`` (divide by ``alpha`` for a normalised depth).
    alpha : Tensor [H, W]        ``1 - T_final``.

    Differentiable w.r.t. means2d, conics, colors, opacities, depths and background.
    """
    cfg = config or CompositeConfig()
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    m = means2d.shape[0]
    if tuple(means2d.shape) != (m, 2) or tuple(conics.shape) != (m, 3) or tuple(colors.shape) != (m, 3):
        raise ValueError(f"bad shapes: means2d {tuple(means2d.shape)}, conics {tuple(conics.shape)}, "
                         f"colors {tuple(colors.shape)} (expected [M,2], [M,3], [M,3])")
    if tuple(opacities.shape) != (m,) or tuple(depths.shape) != (m,):
        raise ValueError(f"opacities {tuple(opacities.shape)} and depths {tuple(depths.shape)} must be [{m}]")
    if tuple(tile_offsets.shape) != (tiles_x * tiles_y + 1,):
        raise ValueError(f"tile_offsets must have {tiles_x * tiles_y + 1} entries for a {width}x{height} image "
                         f"with tile {tile_size}, got {tuple(tile_offsets.shape)}")
    background = background.to(means2d.dtype).reshape(3)
    return _Composite.apply(means2d, conics, colors, opacities, depths, background,
                            isect_ids, tile_offsets, width, height, tile_size, cfg)


# --------------------------------------------------------------------------------------
# Planning: sub-tile lists, which sub-tiles go together, the pixels of a batch.
# --------------------------------------------------------------------------------------
# Relative and absolute (pixels) slack of the culling ellipse: float rounding of sigma
# must never make a culled Gaussian visible at a pixel.
_CULL_REL, _CULL_ABS = 1e-3, 1e-3


@dataclass
class _Grid:
    """Sub-tile geometry: sub-tile s has pixel origin (ox[s], oy[s]) and side ``sub``."""

    sub: int
    ox: Tensor
    oy: Tensor


def _subtile_lists(means2d, conics, opacities, isect_ids, tile_offsets, tiles_x, tile_size, sub):
    """Split every tile's list into its sub-tiles' lists, dropping Gaussians that cannot reach them.

    Returns (ids [I'], offsets [S+1], _Grid).  Sub-tile ``k * T + t`` is the k-th
    (row-major) sub-tile of tile t: with this numbering the lists come out in order by
    filtering the [n_sub, I] candidate matrix row by row, and keep the depth order.
    """
    device = isect_ids.device
    m_side = tile_size // sub
    n_sub = m_side * m_side
    n_tiles = tile_offsets.shape[0] - 1
    k = torch.arange(n_sub, device=device)
    tiles = torch.arange(n_tiles, device=device)
    ox = ((tiles % tiles_x) * tile_size)[None, :] + ((k % m_side) * sub)[:, None]
    oy = ((tiles // tiles_x) * tile_size)[None, :] + ((k // m_side) * sub)[:, None]
    grid = _Grid(sub, ox.reshape(-1), oy.reshape(-1))
    n_isect = isect_ids.shape[0]
    if n_isect == 0:
        return isect_ids, torch.zeros(n_tiles * n_sub + 1, dtype=torch.int64, device=device), grid

    with torch.no_grad():
        a, b, c = conics.unbind(-1)
        det = a * c - b * b
        level = torch.log(opacities.clamp_min(1e-30) / ALPHA_MIN)   # alpha >= ALPHA_MIN <=> sigma <= level
        pd = (a > 0) & (det > 0)
        two_l = 2 * level.clamp_min(0)
        ex = torch.sqrt(two_l * c / det) * (1 + _CULL_REL) + _CULL_ABS
        ey = torch.sqrt(two_l * a / det) * (1 + _CULL_REL) + _CULL_ABS
        # Not positive definite (sigma may be < 0): no culling.  NaN: no culling either (never drawn).
        ex = torch.nan_to_num(torch.where(pd, ex, math.inf), nan=math.inf)
        ey = torch.nan_to_num(torch.where(pd, ey, math.inf), nan=math.inf)
        # Positive definite and fainter than ALPHA_MIN even at the centre: culled everywhere.
        drawable = ~pd | (level > -_CULL_REL)
        lo_x, hi_x = means2d[:, 0] - ex, means2d[:, 0] + ex
        lo_y, hi_y = means2d[:, 1] - ey, means2d[:, 1] + ey

        counts = tile_offsets[1:] - tile_offsets[:-1]
        tile_of = torch.repeat_interleave(tiles, counts, output_size=n_isect)
        g = isect_ids
        tile_f = tile_of.to(means2d.dtype)
        x0 = torch.remainder(tile_f, tiles_x) * tile_size
        y0 = torch.div(tile_f, tiles_x, rounding_mode="floor") * tile_size
        glx, ghx, gly, ghy = lo_x[g], hi_x[g], lo_y[g], hi_y[g]
        # The overlap test separates into x and y; a few [I] vectors per sub-tile column/row.
        in_x = [(glx <= x0 + (j * sub + sub - 0.5)) & (ghx >= x0 + (j * sub + 0.5)) for j in range(m_side)]
        in_y = [(gly <= y0 + (j * sub + sub - 0.5)) & (ghy >= y0 + (j * sub + 0.5)) & drawable[g]
                for j in range(m_side)]
        keep = torch.stack([in_y[kk // m_side] & in_x[kk % m_side] for kk in range(n_sub)])   # [n_sub, I]
        kk, j = keep.nonzero().unbind(1)   # row-major: by sub-tile, then in the tile's depth order
        sub_ids = g[j]
        sid = kk * n_tiles + tile_of[j]
        offsets = torch.searchsorted(sid, torch.arange(n_tiles * n_sub + 1, device=device))
    return sub_ids, offsets, grid


@dataclass
class _Batch:
    subtiles: Tensor  # [B] sub-tile ids, sorted by decreasing count
    starts: Tensor    # [B] first entry of each sub-tile's list
    counts: Tensor    # [B] list lengths
    max_count: int


def _plan(offsets: Tensor, tile_pixels: int, cfg: CompositeConfig) -> list[_Batch]:
    counts = offsets[1:] - offsets[:-1]
    ids = torch.nonzero(counts > 0).squeeze(1)
    if ids.numel() == 0:
        return []
    c = counts[ids]
    order = torch.argsort(c, descending=True, stable=True)
    ids, c = ids[order], c[order]
    starts = offsets[:-1][ids]
    c_list = c.tolist()
    batches, i = [], 0
    while i < len(c_list):  # one iteration per batch, not per tile
        k = min(cfg.chunk, c_list[i])
        b = max(1, cfg.batch_elements // (tile_pixels * k))
        batches.append(_Batch(ids[i:i + b], starts[i:i + b], c[i:i + b], c_list[i]))
        i += b
    return batches


@dataclass
class _Pixels:
    """The pixels of a batch of sub-tiles."""

    cx: Tensor       # [B] sub-tile centre x (pixels), the origin of the local coordinates
    cy: Tensor       # [B]
    inside: Tensor   # [B, P] bool, pixel inside the image
    flat: Tensor     # [B, P] flat image index, H*W for pixels outside
    monomials: Tensor  # [B, P, 6] (1, x, y, x^2, xy, y^2) of local pixel-centre coordinates


def _pixels(subtiles: Tensor, grid: _Grid, width: int, height: int, dtype) -> _Pixels:
    device = subtiles.device
    s = grid.sub
    local = torch.arange(s * s, device=device)
    lx, ly = local % s, local // s
    ox, oy = grid.ox[subtiles], grid.oy[subtiles]
    ix, iy = ox[:, None] + lx[None], oy[:, None] + ly[None]
    inside = (ix < width) & (iy < height)
    flat = torch.where(inside, iy * width + ix, torch.full_like(ix, width * height))
    # Coordinates relative to the sub-tile centre keep the monomials small (|x| < s/2).
    x = (lx.to(dtype) + 0.5) - s / 2
    y = (ly.to(dtype) + 0.5) - s / 2
    mono = torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], dim=-1)
    return _Pixels(ox.to(dtype) + s / 2, oy.to(dtype) + s / 2, inside, flat,
                   mono.expand(subtiles.shape[0], -1, -1).contiguous())


def _threshold_below(value: float, dtype) -> float:
    """The largest number of ``dtype`` below ``value``: ``x > it`` is ``x >= value`` in that dtype."""
    v = torch.tensor(value, dtype=dtype)
    return float(torch.nextafter(v, torch.zeros((), dtype=dtype)))


class _Chunk:
    """One [L, P, K] block (L sub-tiles, P pixels, K Gaussians): what both passes need.

    Per (sub-tile, Gaussian): ``gid``, colour+depth ``cz``, ``opac``, ``conic`` and the
    Gaussian centre relative to the sub-tile centre ``mloc``.  Per (sub-tile, pixel,
    Gaussian): ``raw`` = opacity exp(-sigma), ``alpha`` (0 where skipped, clamped),
    exclusive transmittance ``T_excl``, ``keep`` (1 before the pixel's stop, else 0) and
    the blending weight ``w``.  Per pixel: ``T_new`` and ``active_new`` for the next chunk.
    """

    __slots__ = ("gid", "cz", "opac", "mloc", "conic", "raw", "alpha", "T_excl", "keep", "w",
                 "T_new", "active_new")

    def __init__(self, gid, pix_mono, cx, cy, T_eff, T, ext, alpha_min_below):
        means2d, conics, opacities, cz = ext
        self.gid = gid
        self.cz = cz[gid]                                        # [L, K, 4] colour and depth
        self.opac = opacities[gid]                               # [L, K]
        self.conic = conics[gid]                                 # [L, K, 3]
        mean = means2d[gid]
        mx, my = mean[..., 0] - cx[:, None], mean[..., 1] - cy[:, None]   # local Gaussian centre
        self.mloc = (mx, my)
        a, b, c = self.conic.unbind(-1)
        # ln(o) - sigma(x, y) = k0 + kx x + ky y + kxx x^2 + kxy xy + kyy y^2
        log_o = torch.log(self.opac.clamp_min(1e-30))
        coef = torch.stack([
            log_o - 0.5 * a * mx * mx - b * mx * my - 0.5 * c * my * my,
            a * mx + b * my,
            b * mx + c * my,
            -0.5 * a,
            -b,
            -0.5 * c,
        ], dim=1)                                                # [L, 6, K]
        exponent = torch.bmm(pix_mono, coef)                     # [L, P, K]
        raw = exponent.exp_()                                    # alpha before the skip and the clamp
        alpha = F.threshold(raw, alpha_min_below, 0.0).clamp_max_(ALPHA_MAX)
        pd = (a > 0) & (a * c - b * b > 0)
        if not bool(pd.all()):
            # sigma < 0 is only possible for a conic that is not positive definite.
            sigma_ok = torch.ge(log_o[:, None, :] - torch.log(raw), 0).to(alpha.dtype)
            alpha = alpha * torch.where(pd[:, None, :], torch.ones_like(sigma_ok), sigma_ok)
        L, P, K = alpha.shape
        # Exclusive and inclusive transmittance from one cumulative product over [T, 1 - alpha_1, ...].
        prod = torch.empty(L, P, K + 1, dtype=alpha.dtype, device=alpha.device)
        prod[:, :, 0] = T_eff
        torch.sub(1.0, alpha, out=prod[:, :, 1:])
        prod = torch.cumprod(prod, dim=-1)
        T_excl, C_incl = prod[:, :, :-1], prod[:, :, 1:]
        keep = torch.ge(C_incl, T_STOP, out=torch.empty_like(alpha))  # 1 before the stop, 0 from it on
        self.w = alpha * T_excl * keep
        # Transmittance after the last kept Gaussian: C at the end of the kept prefix (T if none).
        n_keep = keep.sum(dim=-1)
        last = C_incl.gather(-1, (n_keep.long() - 1).clamp_min(0)[:, :, None]).squeeze(-1)
        self.T_new = torch.where(n_keep > 0, last, T)
        self.active_new = keep[:, :, -1] > 0
        self.raw, self.alpha, self.T_excl, self.keep = raw, alpha, T_excl, keep


def _chunks(batch: _Batch, ids: Tensor, m: int, pix: _Pixels, ext, cfg: CompositeConfig, alpha_min_below: float):
    """Replay a batch chunk by chunk; yields (live positions in the batch, _Chunk).

    Both passes see identical state sequences (the generator owns T and the active flags).
    """
    device = ids.device
    n_ids = ids.shape[0]
    dtype = pix.monomials.dtype
    B, P = pix.inside.shape
    T = torch.ones(B, P, dtype=dtype, device=device)
    active = pix.inside.clone()
    live = torch.arange(B, device=device)
    counts, starts = batch.counts, batch.starts
    k0 = 0
    while live.numel() > 0 and k0 < batch.max_count:
        k = min(cfg.chunk, int(counts[live[0]]) - k0)  # live stays sorted by decreasing count
        ar = torch.arange(k0, k0 + k, device=device)
        pos = starts[live, None] + ar[None]
        gid = torch.where(ar[None] < counts[live, None], ids[pos.clamp_max(n_ids - 1)], m)
        T_live, act_live = T[live], active[live]
        ch = _Chunk(gid, pix.monomials[:live.shape[0]], pix.cx[live], pix.cy[live], T_live * act_live, T_live,
                    ext, alpha_min_below)
        yield live, ch
        T[live] = ch.T_new
        active[live] = act_live & ch.active_new
        k0 += k
        still = active[live].any(dim=1) & (counts[live] > k0)
        live = live[still]


def _extended(means2d, conics, colors, opacities, depths):
    """Inputs with one extra Gaussian (index M) used as padding: opacity 0 is never drawn."""
    def ext(x):
        return torch.cat([x, x.new_zeros((1,) + x.shape[1:])])
    conics_ext = torch.cat([conics, conics.new_tensor([[1.0, 0.0, 1.0]])])  # positive definite: no sigma check
    return ext(means2d), conics_ext, ext(opacities), ext(torch.cat([colors, depths[:, None]], dim=1))


def _subtile_size(tile_size: int, cfg: CompositeConfig) -> int:
    return cfg.subtile if 0 < cfg.subtile <= tile_size and tile_size % cfg.subtile == 0 else tile_size


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, background, isect_ids, tile_offsets,
                width, height, tile_size, cfg):
        dtype, device = means2d.dtype, means2d.device
        m = means2d.shape[0]
        tiles_x, _ = tile_grid(width, height, tile_size)
        sub = _subtile_size(tile_size, cfg)
        ids, offsets, grid = _subtile_lists(means2d, conics, opacities, isect_ids, tile_offsets, tiles_x,
                                            tile_size, sub)
        ext = _extended(means2d, conics, colors, opacities, depths)
        below = _threshold_below(ALPHA_MIN, dtype)
        n_pix = width * height
        acc = torch.zeros(n_pix + 1, 4, dtype=dtype, device=device)   # rgb, depth; last row is a sink
        T_img = torch.ones(n_pix + 1, dtype=dtype, device=device)
        plan = _plan(offsets, sub * sub, cfg)
        for batch in plan:
            pix = _pixels(batch.subtiles, grid, width, height, dtype)
            acc_b = torch.zeros(pix.inside.shape + (4,), dtype=dtype, device=device)
            T_b = torch.ones(pix.inside.shape, dtype=dtype, device=device)
            for live, ch in _chunks(batch, ids, m, pix, ext, cfg, below):
                acc_b[live] += torch.bmm(ch.w, ch.cz)
                T_b[live] = ch.T_new
            acc[pix.flat.reshape(-1)] = acc_b.reshape(-1, 4)
            T_img[pix.flat.reshape(-1)] = T_b.reshape(-1)
        T_final = T_img[:n_pix].reshape(height, width)
        rgb = acc[:n_pix, :3].reshape(height, width, 3) + T_final[:, :, None] * background
        depth = acc[:n_pix, 3].reshape(height, width)
        alpha = 1.0 - T_final
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, ids, rgb, depth, T_final)
        ctx.plan = plan
        ctx.grid = grid
        ctx.geometry = (width, height)
        ctx.cfg = cfg
        return rgb, depth, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, g_rgb, g_depth, g_alpha):
        means2d, conics, colors, opacities, depths, ids, rgb, depth, T_final = ctx.saved_tensors
        width, height = ctx.geometry
        cfg, grid = ctx.cfg, ctx.grid
        dtype, device = means2d.dtype, means2d.device
        m = means2d.shape[0]
        n_pix = width * height
        g_rgb = torch.zeros_like(rgb) if g_rgb is None else g_rgb
        g_depth = torch.zeros_like(depth) if g_depth is None else g_depth
        g_alpha = torch.zeros_like(depth) if g_alpha is None else g_alpha

        g_bg = (g_rgb * T_final[:, :, None]).sum(dim=(0, 1)) if ctx.needs_input_grad[5] else None
        # Per pixel: the upstream gradient (rgb, depth) and R of the module docstring; sink row = 0.
        g4 = torch.cat([g_rgb.reshape(n_pix, 3), g_depth.reshape(n_pix, 1)], dim=1)
        R = (g_rgb * rgb).sum(-1) + g_depth * depth - g_alpha * T_final
        g4 = torch.cat([g4, g4.new_zeros(1, 4)])
        R = torch.cat([R.reshape(-1), R.new_zeros(1)])

        ext = _extended(means2d, conics, colors, opacities, depths)
        below = _threshold_below(ALPHA_MIN, dtype)
        # Per Gaussian: mean (2), conic (3), opacity, colour (3), depth; the last row is the padding sink.
        grads = torch.zeros(m + 1, 10, dtype=dtype, device=device)
        for batch in ctx.plan:
            pix = _pixels(batch.subtiles, grid, width, height, dtype)
            g4_b, R_b = g4[pix.flat], R[pix.flat]
            prefix = torch.zeros(pix.inside.shape, dtype=dtype, device=device)
            for live, ch in _chunks(batch, ids, m, pix, ext, cfg, below):
                g4_l = g4_b[live]
                f = torch.bmm(g4_l, ch.cz.transpose(1, 2))              # [L, P, K]
                p_incl = torch.cumsum(f * ch.w, dim=-1).add_(prefix[live][:, :, None])
                prefix[live] = p_incl[:, :, -1]
                # dL/dalpha = f T_excl - (R - prefix) / (1 - alpha), kept only where composited;
                # then dL/d(ln o - sigma) = dL/dalpha * alpha where alpha == raw (drawn, not clamped).
                # Multiplying by alpha rather than raw keeps an overflowed raw (inf) out of it.
                dl_dalpha = f.mul_(ch.T_excl).sub_(p_incl.neg_().add_(R_b[live][:, :, None]).div_(1.0 - ch.alpha))
                drawn_unclamped = torch.eq(ch.alpha, ch.raw, out=torch.empty_like(ch.raw))
                u = dl_dalpha.mul_(ch.keep).mul_(drawn_unclamped).mul_(ch.alpha)
                gk = torch.bmm(u.transpose(1, 2), pix.monomials[:live.shape[0]])   # [L, K, 6]
                g_cz = torch.bmm(ch.w.transpose(1, 2), g4_l)                       # [L, K, 4]
                g = _chain(gk, ch)
                grads.index_put_((ch.gid.reshape(-1),), torch.cat([g, g_cz], dim=-1).reshape(-1, 10),
                                 accumulate=True)
        grads = grads[:m]
        return (grads[:, 0:2], grads[:, 2:5], grads[:, 6:9], grads[:, 5], grads[:, 9], g_bg,
                None, None, None, None, None, None)


def _chain(gk: Tensor, ch: _Chunk) -> Tensor:
    """Gradients [L, K, 6] (mean x, mean y, a, b, c, opacity) from those of the exponent coefficients."""
    g0, gx, gy, gxx, gxy, gyy = gk.unbind(-1)
    mx, my = ch.mloc
    a, b, c = ch.conic.unbind(-1)
    # The coefficients are k0 = ln o - a mx^2/2 - b mx my - c my^2/2, kx = a mx + b my,
    # ky = b mx + c my, kxx = -a/2, kxy = -b, kyy = -c/2 (local coordinates).
    g_mx = g0 * (-a * mx - b * my) + gx * a + gy * b
    g_my = g0 * (-b * mx - c * my) + gx * b + gy * c
    g_a = g0 * (-0.5 * mx * mx) + gx * mx - 0.5 * gxx
    g_b = g0 * (-mx * my) + gx * my + gy * mx - gxy
    g_c = g0 * (-0.5 * my * my) + gy * my - 0.5 * gyy
    # Composited Gaussians have opacity >= alpha >= ALPHA_MIN; the others have g0 = 0.
    g_o = g0 / ch.opac.clamp_min(1e-30)
    return torch.stack([g_mx, g_my, g_a, g_b, g_c, g_o], dim=-1)
