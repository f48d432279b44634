"""Differentiable front-to-back alpha compositing of 2D Gaussians in pure PyTorch.

`rasterize_tiles` is the fast path. It pairs every depth-sorted splat with each square tile its exact
1/255-alpha box touches, lays the work out as one column of tile pixels per (splat, tile) pair with no padding,
drops pairs hidden behind already-opaque pixels, and composites with a hand-derived backward pass.
`rasterize_dense` evaluates every splat at every pixel; it is the reference the tests and
`benchmarks/rasterizer.py` compare against. Both follow 3DGS: alpha = min(0.99, o exp(power)), alphas below
1/255 are skipped, colour = sum_k c_k alpha_k T_k with T_k = prod_{j<k} (1 - alpha_j) (main paper's
Render(G, P)). Written by hand because gsplat's rasterizer exists only as CUDA kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from tracegs.splat.projection import ALPHA_MIN

ALPHA_MAX = 0.99
OCCLUSION_EPS = 1e-5  # pairs behind transmittance below this change a pixel by less than it
COMPACT_BELOW = 0.75  # drop occluded pairs only when fewer than this fraction survive (compaction has a cost)


def splat_alpha(power: Tensor, opacities: Tensor) -> Tensor:
    """3DGS opacity of a splat at a pixel: min(0.99, o exp(power)), set to 0 below 1/255."""
    alpha = (opacities * power.exp()).clamp(max=ALPHA_MAX)
    return alpha * (alpha >= ALPHA_MIN).to(alpha.dtype)


def composite(power: Tensor, opacities: Tensor, features: Tensor) -> tuple[Tensor, Tensor]:
    """Composite splats ordered front to back along the last axis of `power` [..., P, K].

    `opacities` broadcasts to [..., 1, K], `features` is [..., K, C]. Returns (sum_k w_k f_k [..., P, C],
    final transmittance [..., P]). Transmittance uses exp(cumsum(log(1 - alpha))): alpha <= 0.99 keeps the
    logarithm finite, and a cumulative sum backpropagates faster than a cumulative product.
    """
    alpha = splat_alpha(power, opacities)
    log_transmittance = torch.log1p(-alpha)
    cumulative = log_transmittance.cumsum(dim=-1)
    weights = alpha * (cumulative - log_transmittance).exp()
    return weights @ features, cumulative[..., -1].exp()


def rasterize_dense(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, width: int,
                    height: int) -> tuple[Tensor, Tensor]:
    """Reference: every splat against every pixel. Inputs sorted front to back; returns ([H,W,C], [H,W])."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=means2d.dtype, device=means2d.device) + 0.5,
                            torch.arange(width, dtype=means2d.dtype, device=means2d.device) + 0.5, indexing="ij")
    dx = xs.reshape(-1, 1) - means2d[:, 0]
    dy = ys.reshape(-1, 1) - means2d[:, 1]
    a, b, c = conics.unbind(-1)
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    out, transmittance = composite(power, opacities, features)
    return out.reshape(height, width, -1), transmittance.reshape(height, width)


@dataclass
class TileBins:
    """(splat, tile) pairs sorted by tile and, within a tile, front to back."""

    splat: Tensor  # [P] splat index of each pair
    tile: Tensor  # [P] tile index of each pair
    first: Tensor  # [tiles] index of each tile's first pair (clamped; meaningless where count == 0)
    last: Tensor  # [tiles] index of each tile's last pair (same caveat)
    count: Tensor  # [tiles] pairs per tile

    @classmethod
    def from_sorted(cls, splat: Tensor, tile: Tensor, num_tiles: int) -> TileBins:
        count = torch.bincount(tile, minlength=num_tiles)
        start = count.cumsum(0) - count
        top = max(tile.shape[0] - 1, 0)
        return cls(splat, tile, start.clamp_max(top), (start + count - 1).clamp(0, top), count)

    def subset(self, keep: Tensor) -> TileBins:
        return TileBins.from_sorted(self.splat[keep], self.tile[keep], self.count.shape[0])


def bin_tiles(means2d: Tensor, extents: Tensor, tiles_x: int, tiles_y: int, tile_size: int) -> TileBins:
    """Pair every (depth-sorted) splat with every tile its box touches."""
    device = means2d.device
    low = ((means2d - extents) / tile_size).floor().long()
    high = ((means2d + extents) / tile_size).floor().long()
    limit = torch.tensor([tiles_x - 1, tiles_y - 1], device=device)
    low = torch.minimum(low.clamp_min(0), limit)
    high = torch.minimum(high.clamp_min(0), limit)
    span = high - low + 1
    counts = span[:, 0] * span[:, 1]
    splat = torch.repeat_interleave(torch.arange(means2d.shape[0], device=device), counts)
    local = torch.arange(splat.shape[0], device=device) - (counts.cumsum(0) - counts)[splat]
    span_x = span[splat, 0]
    tile = (low[splat, 1] + torch.div(local, span_x, rounding_mode="floor")) * tiles_x + low[splat, 0] + local % span_x
    # Splats arrive sorted by depth, so a stable sort by tile keeps the depth order within every tile.
    tile, order = torch.sort(tile, stable=True)
    return TileBins.from_sorted(splat[order], tile, tiles_x * tiles_y)


def _segment_prefix(values: Tensor, bins: TileBins) -> tuple[Tensor, Tensor]:
    """Per-tile inclusive prefix sums of `values` [S,P] along pairs, and per-tile totals [S,tiles].

    One global cumulative sum minus its value just before the tile's first pair; float64 because the global
    running sum grows far beyond the per-tile values.
    """
    cumulative = values.double().cumsum(dim=1)
    occupied = bins.count > 0
    before = torch.where(occupied, cumulative.index_select(1, bins.first) - values.index_select(1, bins.first), 0.0)
    totals = torch.where(occupied, cumulative.index_select(1, bins.last) - before, 0.0)
    return (cumulative - before.index_select(1, bins.tile)).to(values.dtype), totals.to(values.dtype)


class _TileComposite(torch.autograd.Function):
    """Front-to-back compositing of per-(pixel, pair) Gaussian powers with a hand-derived backward.

    Autograd through the same expressions keeps ~15 pixel-by-pair intermediates alive and spends most of its
    time on them; the closed-form gradient needs no transcendental functions:
    dL/dalpha_k = T_k h_k - (sum_{j>k} w_j h_j + T_final dL/dT_final) / (1 - alpha_k), h_k = f_k . dL/dout.
    """

    @staticmethod
    def forward(ctx, power: Tensor, opacities: Tensor, features: Tensor, bins: TileBins) -> tuple[Tensor, Tensor]:
        num_tiles, pixels, pairs = bins.count.shape[0], power.shape[0], power.shape[1]
        alpha = splat_alpha(power, opacities)
        log_transmittance = torch.log1p(-alpha)
        inclusive, log_final = _segment_prefix(log_transmittance, bins)
        exclusive = inclusive.sub_(log_transmittance)
        keep = (exclusive >= math.log(OCCLUSION_EPS)).any(dim=0)
        kept = None
        if keep.sum() < COMPACT_BELOW * pairs:
            kept = keep.nonzero().squeeze(1)
            alpha, exclusive = alpha.index_select(1, kept), exclusive.index_select(1, kept)
            opacities, features, bins = opacities[kept], features[kept], bins.subset(keep)
        transmittance = exclusive.exp_()
        weights = alpha * transmittance
        contributions = weights.T.contiguous()[:, :, None] * features[:, None, :]  # [P,S,C]
        out = features.new_zeros(num_tiles, pixels, features.shape[1]).index_add_(0, bins.tile, contributions)
        final = log_final.exp()  # [S, tiles]
        ctx.bins, ctx.kept, ctx.pairs = bins, kept, pairs
        ctx.save_for_backward(alpha, opacities, transmittance, weights, features, final)
        return out, final

    @staticmethod
    def backward(ctx, grad_out: Tensor, grad_final: Tensor):
        alpha, opacities, transmittance, weights, features, final = ctx.saved_tensors
        bins = ctx.bins
        colour_grad = torch.zeros_like(weights)  # h_k [S,P]
        grad_features = torch.zeros_like(features)
        for channel in range(features.shape[1]):
            if not grad_out[:, :, channel].any():  # e.g. the depth channel when no loss uses depth
                continue
            per_pair = grad_out[:, :, channel].T.contiguous().index_select(1, bins.tile)
            colour_grad.addcmul_(per_pair, features[:, channel])
            grad_features[:, channel] = (per_pair * weights).sum(dim=0)
        inclusive, totals = _segment_prefix(weights * colour_grad, bins)
        behind = (totals + final * grad_final).index_select(1, bins.tile) - inclusive
        grad_alpha = (transmittance * colour_grad).sub_(behind.div_(1.0 - alpha))  # saved tensors stay intact
        # alpha = o exp(power) where it is neither skipped (0) nor clamped (0.99): d alpha = alpha d power,
        # d alpha / d o = alpha / o.
        grad_power = grad_alpha.mul_(alpha).mul_((alpha > 0) & (alpha < ALPHA_MAX))
        grad_opacities = grad_power.sum(dim=0) / opacities
        if ctx.kept is not None:  # occluded pairs get zero gradient
            kept, pairs = ctx.kept, ctx.pairs
            grad_power = grad_power.new_zeros(grad_power.shape[0], pairs).index_copy_(1, kept, grad_power)
            grad_opacities = grad_opacities.new_zeros(pairs).index_copy_(0, kept, grad_opacities)
            grad_features = grad_features.new_zeros(pairs, features.shape[1]).index_copy_(0, kept, grad_features)
        return grad_power, grad_opacities, grad_features, None


def _pair_power(means2d: Tensor, conics: Tensor, bins: TileBins, tiles_x: int, tile_size: int) -> Tensor:
    """Gaussian exponent [tile_size^2, P] at every pixel of every pair's tile.

    power(p) = -1/2 (p - m)^T C^-1 (p - m) is a quadratic in the pixel position: expanded around the tile
    centre it becomes one matmul of 6 per-pair coefficients with 6 pixel monomials (much faster than
    elementwise dx/dy arithmetic; centring keeps the float32 cancellation error near 1e-6).
    """
    dtype, device = means2d.dtype, means2d.device
    half = tile_size / 2.0
    tile = bins.tile
    centres = torch.stack([tile % tiles_x, torch.div(tile, tiles_x, rounding_mode="floor")], dim=-1)
    mx, my = (means2d.index_select(0, bins.splat) - (centres.to(dtype) * tile_size + half)).unbind(-1)
    a, b, c = conics.index_select(0, bins.splat).unbind(-1)
    coefficients = torch.stack([-0.5 * a, -b, -0.5 * c, a * mx + b * my, b * mx + c * my,
                                -0.5 * (a * mx * mx + c * my * my) - b * mx * my])
    offsets = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - half
    py, px = torch.meshgrid(offsets, offsets, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    monomials = torch.stack([px * px, px * py, py * py, px, py, torch.ones_like(px)], dim=-1)
    return monomials @ coefficients


def rasterize_tiles(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                    width: int, height: int, tile_size: int = 4) -> tuple[Tensor, Tensor]:
    """Tile-culled compositing; same inputs and result as `rasterize_dense` plus the splats' `extents` [M,2].

    Pairs behind pixels that are already opaque (transmittance < OCCLUSION_EPS; 3DGS stops at 1e-4) are dropped
    from the colour sum and the backward pass, which changes the image by less than OCCLUSION_EPS.
    """
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    bins = bin_tiles(means2d.detach(), extents, tiles_x, tiles_y, tile_size)
    if bins.splat.shape[0] == 0:  # nothing on screen; stay in the graph so a loss on it backpropagates zeros
        anchor = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + features.sum())
        return anchor + means2d.new_zeros(height, width, features.shape[1]), anchor + means2d.new_ones(height, width)
    power = _pair_power(means2d, conics, bins, tiles_x, tile_size)
    out, final = _TileComposite.apply(power, opacities.index_select(0, bins.splat),
                                      features.index_select(0, bins.splat), bins)

    def untile(x: Tensor) -> Tensor:
        x = x.reshape(tiles_y, tiles_x, tile_size, tile_size, -1).permute(0, 2, 1, 3, 4)
        return x.reshape(tiles_y * tile_size, tiles_x * tile_size, -1)[:height, :width]

    return untile(out), untile(final.T[..., None])[..., 0]
