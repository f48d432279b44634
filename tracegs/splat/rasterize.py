"""Differentiable front-to-back alpha compositing of 2D Gaussians in pure PyTorch.

`rasterize_tiles` is the fast path: it bins depth-sorted splats into square tiles (a splat joins every tile its
exact 1/255-alpha box touches), pads every tile's list to the longest one, and composites all tiles at once with
batched matrix products. `rasterize_dense` evaluates every splat at every pixel; it is the reference the tests
and `benchmarks/rasterizer.py` compare against. Both follow 3DGS: alpha = min(0.99, o exp(power)), alphas below
1/255 are skipped, colour = sum_k c_k alpha_k T_k with T_k = prod_{j<k} (1 - alpha_k) (main paper's
Render(G, P)). Written by hand because gsplat's rasterizer exists only as CUDA kernels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from tracegs.splat.projection import ALPHA_MIN

ALPHA_MAX = 0.99


def composite(power: Tensor, opacities: Tensor, features: Tensor) -> tuple[Tensor, Tensor]:
    """Composite splats ordered front to back along the last axis of `power` [..., P, K].

    `opacities` broadcasts to [..., 1, K], `features` is [..., K, C]. Returns (sum_k w_k f_k [..., P, C],
    final transmittance [..., P]). Transmittance uses exp(cumsum(log(1 - alpha))): alpha <= 0.99 keeps the
    logarithm finite, and a cumulative sum backpropagates faster than a cumulative product.
    """
    alpha = (opacities * power.exp()).clamp(max=ALPHA_MAX)
    alpha = alpha * (alpha >= ALPHA_MIN).to(alpha.dtype)
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


def _tile_table(means2d: Tensor, extents: Tensor, tiles_x: int, tiles_y: int, tile_size: int) -> Tensor:
    """[tiles, K] indices of the splats touching each tile in input (depth) order, padded with len(means2d)."""
    n = means2d.shape[0]
    low = ((means2d - extents) / tile_size).floor().long()
    high = ((means2d + extents) / tile_size).floor().long()
    limit = torch.tensor([tiles_x - 1, tiles_y - 1], device=means2d.device)
    low = torch.minimum(low.clamp_min(0), limit)
    high = torch.minimum(high.clamp_min(0), limit)
    span = high - low + 1
    counts = span[:, 0] * span[:, 1]
    splat_of_pair = torch.repeat_interleave(torch.arange(n, device=means2d.device), counts)
    first_pair = counts.cumsum(0) - counts
    local = torch.arange(splat_of_pair.shape[0], device=means2d.device) - first_pair[splat_of_pair]
    span_x = span[splat_of_pair, 0]
    tile_x = low[splat_of_pair, 0] + local % span_x
    tile_y = low[splat_of_pair, 1] + torch.div(local, span_x, rounding_mode="floor")
    tile = tile_y * tiles_x + tile_x
    # A stable sort by tile keeps the depth order within every tile.
    tile_sorted, order = torch.sort(tile, stable=True)
    num_tiles = tiles_x * tiles_y
    per_tile = torch.bincount(tile, minlength=num_tiles)
    longest = int(per_tile.max()) if per_tile.numel() else 0
    slot = torch.arange(tile_sorted.shape[0], device=means2d.device) - (per_tile.cumsum(0) - per_tile)[tile_sorted]
    table = torch.full((num_tiles, max(longest, 1)), n, dtype=torch.long, device=means2d.device)
    table[tile_sorted, slot] = splat_of_pair[order]
    return table


def rasterize_tiles(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                    width: int, height: int, tile_size: int = 8) -> tuple[Tensor, Tensor]:
    """Tile-culled compositing; same inputs and result as `rasterize_dense` plus the splats' `extents` [M,2]."""
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    dtype, device = means2d.dtype, means2d.device
    channels = features.shape[1]
    table = _tile_table(means2d.detach(), extents, tiles_x, tiles_y, tile_size)

    # One padding splat with zero opacity (and a harmless conic) fills the short tile lists.
    pad_conic = torch.tensor([[1.0, 0.0, 1.0]], dtype=dtype, device=device)
    means_p = torch.cat([means2d, means2d.new_zeros(1, 2)])[table]
    conics_p = torch.cat([conics, pad_conic])[table]
    opacities_p = torch.cat([opacities, opacities.new_zeros(1)])[table]
    features_p = torch.cat([features, features.new_zeros(1, channels)])[table]

    # power(p) = -1/2 (p - m)^T C^-1 (p - m) is a quadratic in the pixel position: expanding it around each
    # tile's centre turns the per-pixel evaluation into one batched matmul of 6 pixel monomials with 6
    # per-(tile, splat) coefficients, which is several times faster than elementwise dx/dy arithmetic.
    half = tile_size / 2.0
    centres_x = torch.arange(tiles_x, dtype=dtype, device=device) * tile_size + half
    centres_y = torch.arange(tiles_y, dtype=dtype, device=device) * tile_size + half
    centres = torch.stack(torch.meshgrid(centres_y, centres_x, indexing="ij")[::-1], dim=-1).reshape(-1, 1, 2)
    mx, my = (means_p - centres).unbind(-1)
    a, b, c = conics_p.unbind(-1)
    coefficients = torch.stack([-0.5 * a, -b, -0.5 * c, a * mx + b * my, b * mx + c * my,
                                -0.5 * (a * mx * mx + c * my * my) - b * mx * my], dim=1)
    offsets = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - half
    py, px = torch.meshgrid(offsets, offsets, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    monomials = torch.stack([px * px, px * py, py * py, px, py, torch.ones_like(px)], dim=-1)
    power = monomials @ coefficients  # [tiles, tile_size^2, K]

    out, transmittance = composite(power, opacities_p[:, None, :], features_p)

    def untile(x: Tensor) -> Tensor:
        x = x.reshape(tiles_y, tiles_x, tile_size, tile_size, -1).permute(0, 2, 1, 3, 4)
        return x.reshape(tiles_y * tile_size, tiles_x * tile_size, -1)[:height, :width]

    return untile(out), untile(transmittance[..., None])[..., 0]
