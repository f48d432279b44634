"""GSFixer's released transformer layout, read off its public model code, for tests that must fail on a drift.

Repository GVCLab/GSFixer, file ``Reconstruction/gsfixer/cogvideo/crosstransformer3d.py`` (class
``CogVideoXCrossTransformer3DModel``, l. 442-858), and the diffusers modules it instantiates; each group of
keys names the lines it comes from. Folders are written from this list alone, never from our model's state
dict, so a renamed, added or dropped module on our side fails to load them.
"""

from __future__ import annotations

import json
import math

import torch
from safetensors.torch import save_file

from tracegs.restorer.config import TransformerConfig


def gsfixer_parameter_shapes(t: TransformerConfig) -> dict[str, tuple[int, ...]]:
    """Every trainable tensor of GSFixer's transformer for a config, name -> shape."""
    d, e, p = t.num_attention_heads * t.attention_head_dim, t.time_embed_dim, t.patch_size
    shapes: dict[str, tuple[int, ...]] = {
        # crosstransformer3d.py l. 545-561: CogVideoXPatchEmbed (Conv2d proj over noisy + control latents,
        # Linear text_proj); in_channels = 2 x latent channels (pipeline: ``in_channels // 2`` latents)
        "patch_embed.proj.weight": (d, 2 * t.latent_channels, p, p),
        "patch_embed.proj.bias": (d,),
        "patch_embed.text_proj.weight": (d, t.text_embed_dim),
        "patch_embed.text_proj.bias": (d,),
        # l. 566-567: Timesteps (no weights) + TimestepEmbedding(inner_dim, time_embed_dim)
        "time_embedding.linear_1.weight": (e, d),
        "time_embedding.linear_1.bias": (e,),
        "time_embedding.linear_2.weight": (e, e),
        "time_embedding.linear_2.bias": (e,),
        # l. 594: norm_final; l. 597-603: AdaLayerNorm(time_embed_dim, 2 x inner_dim); l. 605-612: proj_out
        "norm_final.weight": (d,),
        "norm_final.bias": (d,),
        "norm_out.linear.weight": (2 * d, e),
        "norm_out.linear.bias": (2 * d,),
        "norm_out.norm.weight": (d,),
        "norm_out.norm.bias": (d,),
        "proj_out.weight": (p * p * t.latent_channels, d),
        "proj_out.bias": (p * p * t.latent_channels,),
    }
    # l. 630-631 with l. 168-188: Projector = ``proj`` Linear(in, inner_dim) then ``norm`` LayerNorm(inner_dim)
    for name, width in (("projector_dino", t.ref_2d_dim), ("projector_vggt", t.ref_3d_dim)):
        shapes |= {f"{name}.proj.weight": (d, width), f"{name}.proj.bias": (d,),
                   f"{name}.norm.weight": (d,), f"{name}.norm.bias": (d,)}
    for i in range(t.num_layers):
        block = f"transformer_blocks.{i}"
        # l. 247 / 274: CogVideoXLayerNormZero(time_embed_dim, dim): Linear(e, 6 dim) + LayerNorm(dim)
        for norm in ("norm1", "norm2"):
            shapes |= {f"{block}.{norm}.linear.weight": (6 * d, e), f"{block}.{norm}.linear.bias": (6 * d,),
                       f"{block}.{norm}.norm.weight": (d,), f"{block}.{norm}.norm.bias": (d,)}
        # l. 249-258 (attn1: diffusers Attention, qk_norm layer_norm) and l. 263-271 with l. 39-85 (attn_cross:
        # their CrossAttention, the same names; keys/values from tokens already at the hidden width)
        for attn in ("attn1", "attn_cross"):
            for proj in ("to_q", "to_k", "to_v", "to_out.0"):
                shapes |= {f"{block}.{attn}.{proj}.weight": (d, d), f"{block}.{attn}.{proj}.bias": (d,)}
            for norm in ("norm_q", "norm_k"):
                shapes |= {f"{block}.{attn}.{norm}.weight": (t.attention_head_dim,),
                           f"{block}.{attn}.{norm}.bias": (t.attention_head_dim,)}
        # l. 261: norm_cross LayerNorm(dim); l. 276-283: FeedForward(dim) -> net.0.proj (GELU-tanh), net.2
        shapes |= {f"{block}.norm_cross.weight": (d,), f"{block}.norm_cross.bias": (d,),
                   f"{block}.ff.net.0.proj.weight": (4 * d, d), f"{block}.ff.net.0.proj.bias": (4 * d,),
                   f"{block}.ff.net.2.weight": (d, 4 * d), f"{block}.ff.net.2.bias": (d,)}
    return shapes


def gsfixer_state_shapes(t: TransformerConfig) -> dict[str, tuple[int, ...]]:
    """The checkpoint's tensors: the parameters plus CogVideoXPatchEmbed's persistent learned positional
    embedding (l. 559-560: ``use_learned_positional_embeddings``, true for CogVideoX-5b-I2V's config)."""
    shapes = gsfixer_parameter_shapes(t)
    if t.use_learned_positional_embeddings:
        frames = (t.sample_frames - 1) // t.temporal_compression_ratio + 1
        patches = frames * (t.sample_height // t.patch_size) * (t.sample_width // t.patch_size)
        shapes["patch_embed.pos_embedding"] = (1, t.max_text_seq_length + patches,
                                               t.num_attention_heads * t.attention_head_dim)
    return shapes


def random_tensors(shapes: dict[str, tuple[int, ...]], seed: int) -> dict[str, torch.Tensor]:
    """Random weights of a trained network's scale: matrices ~ N(0, 1 / fan_in), LayerNorm gains near 1, small
    biases and positional embeddings, so a tiny random restorer stays finite in bf16."""
    generator = torch.Generator().manual_seed(seed)
    tensors = {}
    for key, shape in shapes.items():
        value = torch.randn(shape, generator=generator)
        if len(shape) >= 2 and key != "patch_embed.pos_embedding":
            value = value / math.sqrt(math.prod(shape[1:]))
        elif key.endswith("weight"):  # 1-D weights are LayerNorm gains
            value = 1.0 + 0.1 * value
        else:
            value = 0.1 * value
        tensors[key] = value
    return tensors


def write_gsfixer_folder(folder, t: TransformerConfig, seed: int = 0) -> dict[str, torch.Tensor]:
    """A GSFixer transformer folder as ``save_pretrained`` writes a sharded one: config.json (their class name
    and __init__ keys, l. 503-533), two safetensors shards and the index that maps every key to its shard."""
    tensors = random_tensors(gsfixer_state_shapes(t), seed)
    folder.mkdir(parents=True, exist_ok=True)
    config = {
        "_class_name": "CogVideoXCrossTransformer3DModel", "_diffusers_version": "0.32.1",
        "num_attention_heads": t.num_attention_heads, "attention_head_dim": t.attention_head_dim,
        "in_channels": 2 * t.latent_channels, "out_channels": t.latent_channels, "flip_sin_to_cos": True,
        "freq_shift": 0, "time_embed_dim": t.time_embed_dim, "ofs_embed_dim": None,
        "text_embed_dim": t.text_embed_dim, "num_layers": t.num_layers, "dropout": 0.0, "attention_bias": True,
        "sample_width": t.sample_width, "sample_height": t.sample_height, "sample_frames": t.sample_frames,
        "patch_size": t.patch_size, "patch_size_t": None, "temporal_compression_ratio": t.temporal_compression_ratio,
        "max_text_seq_length": t.max_text_seq_length, "activation_fn": "gelu-approximate",
        "timestep_activation_fn": "silu", "norm_elementwise_affine": True, "norm_eps": 1e-5,
        "spatial_interpolation_scale": 1.875, "temporal_interpolation_scale": 1.0,
        "use_rotary_positional_embeddings": t.use_rotary_positional_embeddings,
        "use_learned_positional_embeddings": t.use_learned_positional_embeddings, "patch_bias": True,
    }
    (folder / "config.json").write_text(json.dumps(config, indent=2))
    keys = sorted(tensors)
    shards = {"diffusion_pytorch_model-00001-of-00002.safetensors": keys[: len(keys) // 2],
              "diffusion_pytorch_model-00002-of-00002.safetensors": keys[len(keys) // 2:]}
    for name, part in shards.items():
        save_file({k: tensors[k].contiguous() for k in part}, folder / name, metadata={"format": "pt"})
    index = {"metadata": {"total_size": sum(v.numel() * 4 for v in tensors.values())},
             "weight_map": {k: name for name, part in shards.items() for k in part}}
    (folder / "diffusion_pytorch_model.safetensors.index.json").write_text(json.dumps(index))
    return tensors
