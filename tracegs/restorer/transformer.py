"""Reference-guided CogVideoX DiT (supplement A.1-A.2), extending diffusers' ``CogVideoXTransformer3DModel``.

What is added to CogVideoX, and nothing else:
- the patch embedding sees ``Concat_ch[xi, Enc_VAE(R_b)]`` (supplement Eq. supp-render-cond), i.e.
  ``in_channels = 2 x out_channels`` as in CogVideoX-I2V;
- reference tokens ``T_ref = Proj_2D(ref_2d) + Proj_3D(ref_3d)`` (Eq. supp-ref-fusion / supp-ref-tokens);
- in every block, a reference cross-attention between the joint self-attention and the feed-forward network,
  queries from video tokens, keys/values from ``T_ref``;
- optional read-out of the final block's retrieval response F (main paper Eq. 7, Eq. supp-retrieval-readout).
Time embedding, patch/positional embeddings, AdaLN, output head and unpatchify are diffusers' own code.

Module names are those of GSFixer's released restorer, so its transformer folder loads as it is: per block
``norm_cross`` + ``attn_cross`` (a residual without gate, per-head q/k LayerNorm with eps 1e-6), and the
projectors ``projector_dino`` / ``projector_vggt`` (``proj`` Linear then ``norm`` LayerNorm each), summed.
With ``reference_norms=False`` (the embedded restorer) the q/k and projector LayerNorms are left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from diffusers import CogVideoXTransformer3DModel
from diffusers.configuration_utils import register_to_config
from diffusers.models.attention_processor import Attention
from diffusers.models.transformers.cogvideox_transformer_3d import CogVideoXBlock
from torch import nn

# What the output head predicts. "velocity": v directly (CogVideoX). "clean": the clean latent x0;
# "residual": x0 minus the conditioning latent (the correction to the rendering). The last two are turned
# into the rectified-flow velocity v = (z_t - x0) / t inside ``forward`` (see ``velocity_from_clean``).
# "preconditioned": EDM's preconditioning around the rendering (see ``Preconditioning``).
PREDICTIONS = ("velocity", "clean", "residual", "preconditioned")


@dataclass
class Preconditioning:
    """EDM's preconditioning (Karras et al. 2022, Sec. 5 and Table 1) of a rectified-flow restorer, centred on
    its rendering R: the network learns only what neither R nor the state z_t already says.

    With z_t = (1 - t) x0 + t sigma_n eps (``noise_scale`` sigma_n: the schedule's noise end), the shifted state
    s = z_t - (1 - t) R = (1 - t)(x0 - R) + t sigma_n eps is a scaled variance-exploding state of the residual
    x0 - R, whose standard deviation is ``sigma_data``. With D = (1 - t)^2 sigma_data^2 + t^2 sigma_n^2 (the
    variance of s):

        x0_hat = R + c_skip s + c_out F(c_in s),   c_skip = (1 - t) sigma_data^2 / D,
        c_out = t sigma_n sigma_data / sqrt(D),   c_in = 1 / sqrt(D),

    so the network's input has unit variance at every t, and its output is scaled by what z_t cannot tell.
    At t = 1 x0_hat = R + sigma_data F (the prediction from R alone); as t -> 0, c_skip -> 1 and c_out -> 0, so
    x0_hat -> z_t for any network output: the last steps only refine, and no error is divided by t.
    The velocity v = (z_t - x0_hat) / t is written without the division (``velocity``):
    v = (t sigma_n^2 - (1 - t) sigma_data^2) / D s - R - sigma_n sigma_data / sqrt(D) F, finite on [0, 1].
    """

    sigma_data: float
    noise_scale: float = 1.0

    def variance(self, t: torch.Tensor) -> torch.Tensor:
        return (1.0 - t) ** 2 * self.sigma_data**2 + t**2 * self.noise_scale**2

    def shifted(self, noisy: torch.Tensor, cond: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """s = z_t - (1 - t) R, the state of the residual x0 - R."""
        return noisy - (1.0 - t) * cond

    def c_in(self, t: torch.Tensor) -> torch.Tensor:
        return self.variance(t).rsqrt()

    def loss_weight(self, t: torch.Tensor) -> torch.Tensor:
        """EDM's loss weight 1 / c_out^2 for an error measured in velocity units, relative to its value at t = 1:
        the velocity error is c_out / t times the output's, so D / sigma_n^2 makes the output's error count alike
        at every t (from sigma_data^2 / sigma_n^2 at t = 0 to 1 at t = 1)."""
        return self.variance(t) / self.noise_scale**2

    def velocity(self, shifted: torch.Tensor, cond: torch.Tensor, output: torch.Tensor,
                 t: torch.Tensor) -> torch.Tensor:
        """v = (z_t - x0_hat) / t of the network output F, in the form without 1 / t."""
        variance = self.variance(t)
        skip = (t * self.noise_scale**2 - (1.0 - t) * self.sigma_data**2) / variance
        return skip * shifted - cond - self.noise_scale * self.sigma_data * variance.rsqrt() * output


def velocity_from_clean(noisy: torch.Tensor, clean: torch.Tensor, t: torch.Tensor, min_time: float) -> torch.Tensor:
    """Rectified-flow velocity of a clean-latent prediction: z_t = (1 - t) x0 + t eps gives
    v = eps - x0 = (z_t - x0) / t.

    Why a small restorer predicts x0 (or x0 - cond) and not v: v = eps - x0 makes the head reproduce the noise
    it was given, about as many numbers per token as its width at the embedded scale, and it cannot do so
    precisely (Li & He 2025, "Back to Basics: Let Denoising Generative Models Denoise"). Measured on the
    embedded benchmark, the residual form restores held-out clips best: the head only has to learn the
    correction to the rendering it sees. ``t`` is clamped at ``min_time`` in the division, as Li & He do, so v
    stays finite near t = 0. Everything downstream still sees a velocity, so the losses of main paper
    Eqs. 3-9 and the solver are unchanged.
    """
    t = t.to(noisy.dtype).clamp_min(min_time).reshape(-1, *([1] * (noisy.dim() - 1)))
    return (noisy - clean) / t


@dataclass
class RestorerOutput:
    velocity: torch.Tensor  # (B, f, C, h, w)
    retrieval: torch.Tensor | None  # (B, n_vid, d): final block's F before to_out.0, or None


class ReferenceAttnProcessor:
    """Multi-head cross-attention video tokens -> reference tokens that can hand out its pre-projection output.

    A processor of our own because the retrieval response F (softmax(Q K^T / sqrt(d_h)) V, heads concatenated,
    *before* ``to_out.0``) is not exposed by diffusers' stock processors.
    """

    def __call__(
        self,
        attn: Attention,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor,
        attention_mask: torch.Tensor | None = None,
        retrieval_sink: dict[str, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        batch, tokens, _ = hidden_states.shape
        query = attn.to_q(hidden_states)
        key = attn.to_k(encoder_hidden_states)
        value = attn.to_v(encoder_hidden_states)
        head_dim = query.shape[-1] // attn.heads

        def heads(x: torch.Tensor) -> torch.Tensor:
            return x.view(batch, -1, attn.heads, head_dim).transpose(1, 2)

        query, key = heads(query), heads(key)
        if attn.norm_q is not None:  # per-head LayerNorm of queries and keys (GSFixer's reference attention)
            query, key = attn.norm_q(query), attn.norm_k(key)
        response = F.scaled_dot_product_attention(query, key, heads(value), attn_mask=attention_mask)
        response = response.transpose(1, 2).reshape(batch, tokens, attn.heads * head_dim)
        if retrieval_sink is not None:
            retrieval_sink["retrieval"] = response
        return attn.to_out[1](attn.to_out[0](response))


class ReferenceGuidedBlock(CogVideoXBlock):
    """CogVideoX block with a reference cross-attention between self-attention and feed-forward (supp. A.1 ii).

    ``forward`` restates the parent's few lines because diffusers offers no hook between the two sublayers.
    Reference tokens travel in ``attention_kwargs['reference_tokens']`` so the parent model's forward (block
    loop, gradient checkpointing) is reused unchanged.
    """

    def __init__(
        self,
        dim: int,
        num_attention_heads: int,
        attention_head_dim: int,
        time_embed_dim: int,
        reference_norms: bool = True,
        **kwargs,
    ):
        super().__init__(dim, num_attention_heads, attention_head_dim, time_embed_dim, **kwargs)
        norm_eps = kwargs.get("norm_eps", 1e-5)
        elementwise_affine = kwargs.get("norm_elementwise_affine", True)
        self.norm_cross = nn.LayerNorm(dim, norm_eps, elementwise_affine)
        self.attn_cross = Attention(
            query_dim=dim,
            cross_attention_dim=dim,  # T_ref is already projected to the hidden width (square LoRA factors)
            dim_head=attention_head_dim,
            heads=num_attention_heads,
            qk_norm="layer_norm" if reference_norms else None,
            eps=1e-6,
            bias=kwargs.get("attention_bias", False),
            out_bias=kwargs.get("attention_out_bias", True),
            processor=ReferenceAttnProcessor(),
        )

    def forward(
        self,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor,
        temb: torch.Tensor,
        image_rotary_emb: tuple[torch.Tensor, torch.Tensor] | None = None,
        attention_kwargs: dict[str, Any] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        attention_kwargs = dict(attention_kwargs or {})
        reference_tokens = attention_kwargs.pop("reference_tokens")
        retrieval_sink = attention_kwargs.pop("retrieval_sink", None)
        text_length = encoder_hidden_states.size(1)

        # (i) joint 3D self-attention over video + text tokens, AdaLN-modulated (as in CogVideoXBlock)
        norm_hidden, norm_text, gate_msa, text_gate_msa = self.norm1(
            hidden_states, encoder_hidden_states, temb
        )
        attn_hidden, attn_text = self.attn1(
            hidden_states=norm_hidden,
            encoder_hidden_states=norm_text,
            image_rotary_emb=image_rotary_emb,
            **attention_kwargs,
        )
        hidden_states = hidden_states + gate_msa * attn_hidden
        encoder_hidden_states = encoder_hidden_states + text_gate_msa * attn_text

        # (ii) reference cross-attention: video-token queries, T_ref keys/values (supp. Eq. supp-retrieval-qkv),
        # added without an AdaLN gate
        hidden_states = hidden_states + self.attn_cross(
            self.norm_cross(hidden_states),
            encoder_hidden_states=reference_tokens,
            retrieval_sink=retrieval_sink,
        )

        # (iii) feed-forward over video + text tokens (as in CogVideoXBlock)
        norm_hidden, norm_text, gate_ff, text_gate_ff = self.norm2(hidden_states, encoder_hidden_states, temb)
        ff_output = self.ff(torch.cat([norm_text, norm_hidden], dim=1))
        hidden_states = hidden_states + gate_ff * ff_output[:, text_length:]
        encoder_hidden_states = encoder_hidden_states + text_gate_ff * ff_output[:, :text_length]
        return hidden_states, encoder_hidden_states


class ReferenceProjector(nn.Module):
    """Proj_2D / Proj_3D of Eq. supp-ref-fusion: a Linear to the hidden width, then (GSFixer) a LayerNorm."""

    def __init__(self, in_features: int, width: int, norm: bool):
        super().__init__()
        self.proj = nn.Linear(in_features, width)
        self.norm = nn.LayerNorm(width) if norm else nn.Identity()

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return self.norm(self.proj(tokens))


class ReferenceGuidedTransformer(CogVideoXTransformer3DModel):
    """GSFixer's restorer v_theta (supplement A.1); ``in_channels = 2 * out_channels`` (noisy + condition)."""

    _no_split_modules = ["ReferenceGuidedBlock", "CogVideoXPatchEmbed"]

    @register_to_config
    def __init__(
        self,
        num_attention_heads: int = 48,
        attention_head_dim: int = 64,
        in_channels: int = 32,
        out_channels: int | None = 16,
        flip_sin_to_cos: bool = True,
        freq_shift: int = 0,
        time_embed_dim: int = 512,
        ofs_embed_dim: int | None = None,
        text_embed_dim: int = 4096,
        num_layers: int = 42,
        dropout: float = 0.0,
        attention_bias: bool = True,
        sample_width: int = 90,
        sample_height: int = 60,
        sample_frames: int = 49,
        patch_size: int = 2,
        patch_size_t: int | None = None,
        temporal_compression_ratio: int = 4,
        max_text_seq_length: int = 226,
        activation_fn: str = "gelu-approximate",
        timestep_activation_fn: str = "silu",
        norm_elementwise_affine: bool = True,
        norm_eps: float = 1e-5,
        spatial_interpolation_scale: float = 1.875,
        temporal_interpolation_scale: float = 1.0,
        use_rotary_positional_embeddings: bool = True,
        use_learned_positional_embeddings: bool = True,
        patch_bias: bool = True,
        ref_2d_dim: int = 1024,
        ref_3d_dim: int = 2048,
        reference_norms: bool = True,
        timestep_scale: float = 1.0,
        prediction: str = "velocity",
        clean_min_time: float = 0.05,
        sigma_data: float = 1.0,
        noise_scale: float = 1.0,
    ):
        if prediction not in PREDICTIONS:
            raise ValueError(f"transformer prediction={prediction!r} must be one of {PREDICTIONS}")
        if out_channels is None or in_channels != 2 * out_channels:
            raise ValueError(
                f"transformer in_channels={in_channels} must be 2 x out_channels={out_channels} "
                "(noisy latent concatenated with the rendered-sequence latent)"
            )
        # The parent builds everything but the blocks (num_layers=0); ours replace CogVideoXBlock.
        super().__init__(
            num_attention_heads=num_attention_heads,
            attention_head_dim=attention_head_dim,
            in_channels=in_channels,
            out_channels=out_channels,
            flip_sin_to_cos=flip_sin_to_cos,
            freq_shift=freq_shift,
            time_embed_dim=time_embed_dim,
            ofs_embed_dim=ofs_embed_dim,
            text_embed_dim=text_embed_dim,
            num_layers=0,
            dropout=dropout,
            attention_bias=attention_bias,
            sample_width=sample_width,
            sample_height=sample_height,
            sample_frames=sample_frames,
            patch_size=patch_size,
            patch_size_t=patch_size_t,
            temporal_compression_ratio=temporal_compression_ratio,
            max_text_seq_length=max_text_seq_length,
            activation_fn=activation_fn,
            timestep_activation_fn=timestep_activation_fn,
            norm_elementwise_affine=norm_elementwise_affine,
            norm_eps=norm_eps,
            spatial_interpolation_scale=spatial_interpolation_scale,
            temporal_interpolation_scale=temporal_interpolation_scale,
            use_rotary_positional_embeddings=use_rotary_positional_embeddings,
            use_learned_positional_embeddings=use_learned_positional_embeddings,
            patch_bias=patch_bias,
        )
        # diffusers registers the config before __init__ runs, so the parent call above recorded num_layers=0.
        self.register_to_config(num_layers=num_layers)
        inner_dim = num_attention_heads * attention_head_dim
        self.transformer_blocks = nn.ModuleList(
            [
                ReferenceGuidedBlock(
                    inner_dim,
                    num_attention_heads,
                    attention_head_dim,
                    time_embed_dim,
                    reference_norms=reference_norms,
                    dropout=dropout,
                    activation_fn=activation_fn,
                    attention_bias=attention_bias,
                    norm_elementwise_affine=norm_elementwise_affine,
                    norm_eps=norm_eps,
                )
                for _ in range(num_layers)
            ]
        )
        self.projector_dino = ReferenceProjector(ref_2d_dim, inner_dim, reference_norms)  # Proj_2D (DINOv2)
        self.projector_vggt = ReferenceProjector(ref_3d_dim, inner_dim, reference_norms)  # Proj_3D (VGGT)
        self._rotary_cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        if prediction in ("residual", "preconditioned"):
            # A fresh residual restorer starts as the identity on its input rendering (x0 = cond; preconditioned:
            # x0 = cond + c_skip s), like DiT's zero-initialised output layer; training then learns corrections.
            nn.init.zeros_(self.proj_out.weight)
            nn.init.zeros_(self.proj_out.bias)

    def reference_tokens(self, ref_2d: torch.Tensor, ref_3d: torch.Tensor) -> torch.Tensor:
        """T_ref = Proj_2D(ref_2d) + Proj_3D(ref_3d), both views' tokens already concatenated along R."""
        if ref_2d.shape[:2] != ref_3d.shape[:2]:
            raise ValueError(
                f"ref_2d {tuple(ref_2d.shape)} and ref_3d {tuple(ref_3d.shape)} need the same (B, R)"
            )
        dtype = self.projector_dino.proj.weight.dtype
        return self.projector_dino(ref_2d.to(dtype)) + self.projector_vggt(ref_3d.to(dtype))

    def _rotary_embedding(self, frames: int, height: int, width: int, device: torch.device):
        """3D RoPE for a latent grid, computed as CogVideoX's pipelines do (cached per grid)."""
        from diffusers.models.embeddings import get_3d_rotary_pos_embed
        from diffusers.pipelines.cogvideo.pipeline_cogvideox_image2video import (
            get_resize_crop_region_for_grid,
        )

        key = (frames, height, width, str(device))
        if key not in self._rotary_cache:
            p = self.config.patch_size
            grid = (height // p, width // p)
            crops = get_resize_crop_region_for_grid(
                grid, self.config.sample_width // p, self.config.sample_height // p
            )
            self._rotary_cache[key] = get_3d_rotary_pos_embed(
                embed_dim=self.config.attention_head_dim,
                crops_coords=crops,
                grid_size=grid,
                temporal_size=frames,
                device=device,
            )
        return self._rotary_cache[key]

    def forward(
        self,
        noisy: torch.Tensor,
        cond: torch.Tensor,
        timestep: torch.Tensor,
        text: torch.Tensor,
        ref_2d: torch.Tensor,
        ref_3d: torch.Tensor,
        return_retrieval: bool = False,
    ) -> RestorerOutput:
        """Velocity v_theta(xi, t, R_b) (main paper Eq. 3) and optionally F of the final block (Eq. 7).

        ``timestep`` is the schedule's native time (rectified flow t in [0, 1], DDPM step in [0, T-1]); it is
        multiplied by ``config.timestep_scale`` before the sinusoidal embedding. Inputs are cast to the
        weights' dtype; outputs come back in the dtype of ``noisy``.
        """
        if noisy.shape != cond.shape:
            raise ValueError(f"noisy {tuple(noisy.shape)} and cond {tuple(cond.shape)} latents must match")
        batch, frames, _, height, width = noisy.shape
        if (
            not self.config.use_rotary_positional_embeddings
            and text.shape[1] != self.config.max_text_seq_length
        ):
            raise ValueError(
                f"text length {text.shape[1]} must equal max_text_seq_length={self.config.max_text_seq_length}"
            )
        timestep = torch.as_tensor(timestep, device=noisy.device).float().reshape(-1).expand(batch)
        rotary = (
            self._rotary_embedding(frames, height, width, noisy.device)
            if self.config.use_rotary_positional_embeddings
            else None
        )
        sink: dict[str, torch.Tensor] | None = {} if return_retrieval else None
        weights = self.patch_embed.proj.weight.dtype  # e.g. a bf16 base fed float32 cached latents
        network_input = noisy
        if self.config.prediction == "preconditioned":
            precond = Preconditioning(self.config.sigma_data, self.config.noise_scale)
            t = timestep.to(noisy.dtype).reshape(-1, *([1] * (noisy.dim() - 1)))
            shifted = precond.shifted(noisy, cond.to(noisy.dtype), t)
            network_input = precond.c_in(t) * shifted
        velocity = super().forward(
            hidden_states=torch.cat([network_input, cond.to(network_input.dtype)], dim=2).to(weights),
            encoder_hidden_states=text.to(weights),
            timestep=timestep * self.config.timestep_scale,
            image_rotary_emb=rotary,
            attention_kwargs={
                "reference_tokens": self.reference_tokens(ref_2d, ref_3d),
                "retrieval_sink": sink,
            },
            return_dict=False,
        )[0]
        velocity = velocity.to(noisy.dtype)
        if self.config.prediction == "preconditioned":
            velocity = precond.velocity(shifted, cond.to(noisy.dtype), velocity, t)
        elif self.config.prediction != "velocity":
            clean = velocity + cond.to(velocity.dtype) if self.config.prediction == "residual" else velocity
            velocity = velocity_from_clean(noisy, clean, timestep, self.config.clean_min_time)
        retrieval = sink["retrieval"].to(noisy.dtype) if sink is not None else None
        return RestorerOutput(velocity=velocity, retrieval=retrieval)

    def loss_weight(self, timestep: torch.Tensor) -> torch.Tensor:
        """Per-sample weight of the squared velocity error at times ``timestep`` (B,) that makes the network
        output's error count alike at every t (``Preconditioning.loss_weight``; prediction=preconditioned)."""
        if self.config.prediction != "preconditioned":
            raise ValueError("an EDM loss weight needs transformer prediction='preconditioned', got "
                             f"{self.config.prediction!r}")
        return Preconditioning(self.config.sigma_data, self.config.noise_scale).loss_weight(timestep)
