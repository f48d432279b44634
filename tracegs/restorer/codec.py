"""Video codecs mapping pixel clips to the latent space of the restorer (supplement A.1, Enc_VAE).

Layout convention of the whole restorer: pixels ``(B, F, 3, H, W)`` in [0, 1], latents ``(B, f, C, h, w)``
(diffusers' CogVideoX transformer layout; the VAE itself wants ``(B, C, F, H, W)``, so we permute here).
"""

from __future__ import annotations

import math
from typing import Protocol

import torch

from tracegs.restorer.config import CodecConfig
from tracegs.restorer.loading import require_local_dir


class Codec(Protocol):
    latent_channels: int
    spatial_factor: int

    def encode(self, frames: torch.Tensor) -> torch.Tensor: ...

    def decode(self, latents: torch.Tensor) -> torch.Tensor: ...

    def latent_frames(self, num_frames: int) -> int: ...

    def to(self, device: torch.device | str) -> Codec: ...


def _dct_matrix(n: int) -> torch.Tensor:
    """Orthonormal DCT-II matrix (rows are basis vectors)."""
    k = torch.arange(n, dtype=torch.float64)
    m = torch.cos(math.pi * (k[None, :] + 0.5) * k[:, None] / n) * math.sqrt(2.0 / n)
    m[0] /= math.sqrt(2.0)
    return m


class EmbeddedCodec:
    """Fixed orthonormal transform over ``s x s`` pixel blocks, truncated to the C lowest-frequency coefficients.

    Written by hand because no library offers a fast, weight-free, near-lossless latent codec for CPU:
    a 2D DCT-II per block on an orthonormal luma / two-opponent-chroma colour basis, coefficients ranked by the
    square low-pass order ``max(u, v)`` with chroma at half the resolution (key ``2 max(u, v) + 1``, like 4:2:0),
    keeping the first ``latent_channels``. Each kept coefficient is multiplied by ``(1 + u + v) / 2`` so the
    channels have comparable variance (natural-image DCT amplitudes fall roughly as ``1 / (1 + u + v)``);
    otherwise the diffusion loss would ignore the detail channels. No temporal compression: f = F.
    """

    def __init__(self, cfg: CodecConfig, device: torch.device | str = "cpu"):
        s, c = cfg.block_size, cfg.latent_channels
        if not 1 <= c <= 3 * s * s:
            raise ValueError(f"codec.latent_channels={c} must be in [1, {3 * s * s}] for block_size={s}")
        self.cfg = cfg
        self.spatial_factor = s
        self.latent_channels = c
        colour = torch.tensor([[1.0, 1.0, 1.0], [1.0, -1.0, 0.0], [1.0, 1.0, -2.0]], dtype=torch.float64)
        colour = colour / colour.norm(dim=1, keepdim=True)
        dct = _dct_matrix(s)
        basis = torch.kron(colour, torch.kron(dct, dct))  # rows index (colour, u, v); columns index (c, y, x)
        ranked = sorted(
            (max(u, v) if ch == 0 else 2 * max(u, v) + 1, ch, u + v, ch * s * s + u * s + v, 1.0 + u + v)
            for ch in range(3)
            for u in range(s)
            for v in range(s)
        )[:c]
        rows = [entry[3] for entry in ranked]
        gain = torch.tensor([entry[4] / 2.0 for entry in ranked], dtype=torch.float64)
        self._analysis = (basis[rows] * gain[:, None]).float().to(device)  # (C, 3 s s)
        self._synthesis = (basis[rows] / gain[:, None]).float().to(device)  # pseudo-inverse of the analysis

    def to(self, device: torch.device | str) -> EmbeddedCodec:
        self._analysis = self._analysis.to(device)
        self._synthesis = self._synthesis.to(device)
        return self

    def latent_frames(self, num_frames: int) -> int:
        return num_frames

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        b, f, ch, h, w = frames.shape
        s = self.spatial_factor
        if ch != 3 or h % s or w % s:
            raise ValueError(
                f"EmbeddedCodec.encode: frames (B,F,3,H,W) with H, W divisible by {s}, got {tuple(frames.shape)}"
            )
        x = frames.to(self._analysis.dtype) * 2.0 - 1.0
        blocks = (
            x.reshape(b, f, 3, h // s, s, w // s, s)
            .permute(0, 1, 3, 5, 2, 4, 6)
            .reshape(b, f, h // s, w // s, -1)
        )
        return (blocks @ self._analysis.T).permute(0, 1, 4, 2, 3).contiguous()

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        b, f, c, hl, wl = latents.shape
        s = self.spatial_factor
        if c != self.latent_channels:
            raise ValueError(
                f"EmbeddedCodec.decode: expected {self.latent_channels} latent channels, got {c}"
            )
        blocks = latents.to(self._synthesis.dtype).permute(0, 1, 3, 4, 2) @ self._synthesis
        x = (
            blocks.reshape(b, f, hl, wl, 3, s, s)
            .permute(0, 1, 4, 2, 5, 3, 6)
            .reshape(b, f, 3, hl * s, wl * s)
        )
        return ((x + 1.0) * 0.5).clamp(0.0, 1.0)


class CogVideoXCodec:
    """diffusers ``AutoencoderKLCogVideoX`` loaded from a local directory (paper scale, frozen).

    Encoding uses the posterior mode (deterministic caches) times the VAE's ``scaling_factor``, as the
    CogVideoX pipelines feed latents to the transformer.
    """

    def __init__(
        self, cfg: CodecConfig, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
        vae: torch.nn.Module | None = None,
    ):
        """Loads ``cfg.pretrained_path``, or wraps ``vae`` as given (a GPU check times random weights)."""
        from diffusers import AutoencoderKLCogVideoX

        if vae is None:
            if cfg.pretrained_path is None:
                raise ValueError("codec.pretrained_path must name a local AutoencoderKLCogVideoX directory")
            path = require_local_dir(cfg.pretrained_path, "codec.pretrained_path")
            vae = AutoencoderKLCogVideoX.from_pretrained(path, torch_dtype=dtype)
        self.vae = vae.to(device).eval()
        self.vae.requires_grad_(False)
        if cfg.tiling:
            self.vae.enable_tiling()
        self.cfg = cfg
        self.spatial_factor = 2 ** (len(self.vae.config.block_out_channels) - 1)
        self.temporal_factor = int(self.vae.config.temporal_compression_ratio)
        self.latent_channels = int(self.vae.config.latent_channels)
        self.scaling_factor = float(self.vae.config.scaling_factor)

    def to(self, device: torch.device | str) -> CogVideoXCodec:
        self.vae.to(device)
        return self

    def latent_frames(self, num_frames: int) -> int:
        # The causal VAE encodes frames in chunks of 2 x temporal factor after the first; other counts come back
        # with the wrong length after decoding (the CogVideoX VAE's 8k+1 frame contract).
        chunk = 2 * self.temporal_factor
        if (num_frames - 1) % chunk:
            raise ValueError(
                f"CogVideoXCodec needs F = {chunk}k + 1 frames (9, 17, ..., 49), got {num_frames}"
            )
        return 1 + (num_frames - 1) // self.temporal_factor

    @torch.no_grad()
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        self.latent_frames(frames.shape[1])
        x = (frames * 2.0 - 1.0).permute(0, 2, 1, 3, 4).to(self.vae.dtype)
        latents = self.vae.encode(x).latent_dist.mode() * self.scaling_factor
        return latents.permute(0, 2, 1, 3, 4).float()

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        z = (latents / self.scaling_factor).permute(0, 2, 1, 3, 4).to(self.vae.dtype)
        x = self.vae.decode(z).sample
        return ((x.float() + 1.0) * 0.5).clamp(0.0, 1.0).permute(0, 2, 1, 3, 4)


def build_codec(cfg: CodecConfig, device: torch.device | str = "cpu") -> Codec:
    if cfg.kind == "embedded":
        return EmbeddedCodec(cfg, device)
    if cfg.kind == "cogvideox":
        return CogVideoXCodec(cfg, device)
    raise ValueError(f"codec.kind must be 'embedded' or 'cogvideox', got {cfg.kind!r}")
