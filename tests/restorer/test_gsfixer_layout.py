"""GSFixer's released restorer loads into ``ReferenceGuidedTransformer`` as it is, and computes what GSFixer's
block computes.

The key list (``tests/support/gsfixer_layout.py``) is read off GSFixer's public model code, each group with the lines of
``Reconstruction/gsfixer/cogvideo/crosstransformer3d.py`` it comes from; the tiny checkpoint is written from that
list alone, in diffusers' sharded layout. The block below is GSFixer's ``CogVideoXBlock.forward`` written out
with torch.nn.functional from that file, reading the stored tensors (not our modules).
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from support.gsfixer_layout import gsfixer_parameter_shapes, gsfixer_state_shapes, write_gsfixer_folder

from tracegs.restorer import adapters
from tracegs.restorer.build import CheckpointMismatchError, create_transformer, load_transformer
from tracegs.restorer.config import TransformerConfig

TINY = TransformerConfig(
    num_layers=2, num_attention_heads=2, attention_head_dim=16, latent_channels=4, text_embed_dim=12,
    max_text_seq_length=5, time_embed_dim=16, sample_frames=9, sample_height=4, sample_width=6,
    temporal_compression_ratio=4, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
    ref_2d_dim=10, ref_3d_dim=14, reference_norms=True, timestep_scale=1.0,
)


# ---- GSFixer's block, written out with torch.nn.functional from its source, reading the stored tensors ----

def _linear(w, name, x):
    return F.linear(x, w[f"{name}.weight"], w[f"{name}.bias"])


def _layer_norm(w, name, x, eps):
    return F.layer_norm(x, x.shape[-1:], w[f"{name}.weight"], w[f"{name}.bias"], eps)


def _heads(x, heads):
    return x.unflatten(-1, (heads, -1)).transpose(1, 2)


def _rotate(x, cos, sin):
    """CogVideoX's real-valued RoPE: channel pairs (re, im) -> (re cos - im sin, im cos + re sin)."""
    re, im = x.unflatten(-1, (-1, 2)).unbind(-1)
    return x * cos + torch.stack([-im, re], dim=-1).flatten(-2) * sin


def _layer_norm_zero(w, name, video, text, temb, eps):
    """CogVideoXLayerNormZero (l. 247): SiLU -> Linear -> 6 chunks; x -> LN(x) (1 + scale) + shift; gates."""
    shift, scale, gate, t_shift, t_scale, t_gate = _linear(w, f"{name}.linear", F.silu(temb)).chunk(6, dim=1)
    video = _layer_norm(w, f"{name}.norm", video, eps) * (1 + scale[:, None]) + shift[:, None]
    text = _layer_norm(w, f"{name}.norm", text, eps) * (1 + t_scale[:, None]) + t_shift[:, None]
    return video, text, gate[:, None], t_gate[:, None]


def gsfixer_block(w, video, text, cross, temb, rotary, heads, eps=1e-5):
    """CogVideoXBlock.forward of crosstransformer3d.py l. 285-337."""
    n_text = text.shape[1]
    # l. 298-311: AdaLN-zero, joint attention over [text, video] (CogVideoXAttnProcessor2_0: per-head q/k
    # LayerNorm eps 1e-6, RoPE on the video tokens only), gated residuals
    nv, nt, gate, t_gate = _layer_norm_zero(w, "norm1", video, text, temb, eps)
    joint = torch.cat([nt, nv], dim=1)
    q, k, v = (_heads(_linear(w, f"attn1.{p}", joint), heads) for p in ("to_q", "to_k", "to_v"))
    q, k = _layer_norm(w, "attn1.norm_q", q, 1e-6), _layer_norm(w, "attn1.norm_k", k, 1e-6)
    cos, sin = rotary
    q = torch.cat([q[:, :, :n_text], _rotate(q[:, :, n_text:], cos, sin)], dim=2)
    k = torch.cat([k[:, :, :n_text], _rotate(k[:, :, n_text:], cos, sin)], dim=2)
    attn = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1]), dim=-1) @ v
    attn = _linear(w, "attn1.to_out.0", attn.transpose(1, 2).flatten(2))
    video, text = video + gate * attn[:, n_text:], text + t_gate * attn[:, :n_text]
    # l. 313-322 with CrossAttention.forward l. 88-124: norm_cross, q from video, k/v from the reference
    # tokens, per-head LayerNorm eps 1e-6, no RoPE, to_out.0, residual without gate
    q = _heads(_linear(w, "attn_cross.to_q", _layer_norm(w, "norm_cross", video, eps)), heads)
    k, v = (_heads(_linear(w, f"attn_cross.{p}", cross), heads) for p in ("to_k", "to_v"))
    q, k = _layer_norm(w, "attn_cross.norm_q", q, 1e-6), _layer_norm(w, "attn_cross.norm_k", k, 1e-6)
    attn = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1]), dim=-1) @ v
    video = video + _linear(w, "attn_cross.to_out.0", attn.transpose(1, 2).flatten(2))
    # l. 326-335: AdaLN-zero, feed-forward over [text, video] (GELU tanh), gated residuals
    nv, nt, gate, t_gate = _layer_norm_zero(w, "norm2", video, text, temb, eps)
    hidden = F.gelu(_linear(w, "ff.net.0.proj", torch.cat([nt, nv], dim=1)), approximate="tanh")
    ff = _linear(w, "ff.net.2", hidden)
    return video + gate * ff[:, n_text:], text + t_gate * ff[:, :n_text]


def gsfixer_reference_tokens(w, dino, vggt):
    """l. 790-794: projector_dino(dino) + projector_vggt(vggt), each Linear then LayerNorm (l. 186-187)."""
    return sum(_layer_norm(w, f"{name}.norm", _linear(w, f"{name}.proj", x), 1e-5)
               for name, x in (("projector_dino", dino), ("projector_vggt", vggt)))


def test_gsfixer_folder_loads_strictly_with_every_tensor_used(tmp_path):
    stored = write_gsfixer_folder(tmp_path / "transformer", TINY)
    model = load_transformer(replace(TINY, pretrained_path=str(tmp_path / "transformer")))
    state = model.state_dict()
    assert set(state) == set(stored)
    for key, value in stored.items():
        assert torch.equal(state[key], value), key


def test_block_and_projectors_compute_what_gsfixer_computes(tmp_path):
    stored = write_gsfixer_folder(tmp_path / "transformer", TINY)
    model = load_transformer(replace(TINY, pretrained_path=str(tmp_path / "transformer")))
    g = torch.Generator().manual_seed(1)
    d = TINY.num_attention_heads * TINY.attention_head_dim
    frames, h, w = 3, TINY.sample_height, TINY.sample_width
    video = torch.randn(2, frames * (h // 2) * (w // 2), d, generator=g)
    text = torch.randn(2, TINY.max_text_seq_length, d, generator=g)
    temb = torch.randn(2, TINY.time_embed_dim, generator=g)
    dino, vggt = torch.randn(2, 8, TINY.ref_2d_dim, generator=g), torch.randn(2, 8, TINY.ref_3d_dim, generator=g)
    rotary = model._rotary_embedding(frames, h, w, torch.device("cpu"))
    with torch.no_grad():
        cross = model.reference_tokens(dino, vggt)
        ours = model.transformer_blocks[1](video, text, temb, rotary, attention_kwargs={"reference_tokens": cross})
        expected_cross = gsfixer_reference_tokens(stored, dino, vggt)
        block = {k.removeprefix("transformer_blocks.1."): v for k, v in stored.items()}
        theirs = gsfixer_block(block, video, text, expected_cross, temb, rotary, TINY.num_attention_heads)
    assert (cross - expected_cross).abs().max() <= 1e-5
    for mine, reference in zip(ours, theirs):
        assert (mine - reference).abs().max() <= 1e-5


def test_a_folder_that_does_not_map_names_its_first_key_in_one_line(tmp_path):
    stored = write_gsfixer_folder(tmp_path / "transformer", TINY)
    renamed = {k.replace("projector_vggt.norm", "projector_vggt.ln"): v for k, v in stored.items()}
    folder = tmp_path / "renamed"
    folder.mkdir()
    (folder / "config.json").write_text((tmp_path / "transformer" / "config.json").read_text())
    save_file(renamed, folder / "diffusion_pytorch_model.safetensors")
    with pytest.raises(CheckpointMismatchError) as error:
        load_transformer(replace(TINY, pretrained_path=str(folder)))
    message = str(error.value)
    assert "\n" not in message and "'projector_vggt.ln.bias' has no place in the model" in message


def test_paper_shapes_on_the_meta_device_are_gsfixers(paper_backbone):
    t = paper_backbone.transformer
    model = create_transformer(t, "meta")
    assert {n: tuple(p.shape) for n, p in model.named_parameters()} == gsfixer_parameter_shapes(t)
    position = gsfixer_state_shapes(t)["patch_embed.pos_embedding"]
    assert tuple(model.state_dict()["patch_embed.pos_embedding"].shape) == position == (1, 226 + 13 * 30 * 45, 3072)
    adapters.add_adapter(model, "student", paper_backbone.lora)
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    assert trainable == 66_060_288  # supplement Eq. supp-lora-block-params: 42 x 16 x 32 x 3072
    adapted = {n.split(".lora_A")[0].split(".", 2)[2] for n, _ in model.named_parameters() if ".lora_A." in n}
    # supplement's table of adapted projections: to_q, to_k, to_v, to_out.0 of both attentions of every block
    assert adapted == {f"{a}.{p}" for a in ("attn1", "attn_cross") for p in ("to_q", "to_k", "to_v", "to_out.0")}
