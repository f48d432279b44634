"""The bytes a paper-scale deployment / evaluation holds per component and device (restorer/memory.py), counted
on the meta device: equal to the loaded components at the rehearsal's shapes, and the paper's published sizes
at the paper's shapes (config files only: nothing is allocated)."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from support.rehearsal import rehearsal_config

from tracegs.deploy.assembly import restorer_holdings
from tracegs.restorer import adapters
from tracegs.restorer.build import build_backbone
from tracegs.restorer.memory import GIB, device_totals, holdings_table, module_bytes, training_component_bytes

METHODS = ["3dgs", "baseline", "tracegs"]


def test_rehearsal_figure_is_what_the_loaded_components_hold(rehearsal_root, vggt_double):
    cfg = OmegaConf.to_object(rehearsal_config(rehearsal_root, "evaluate").backbone)
    counted = {h.component: h for h in restorer_holdings(cfg, METHODS, None, device="cpu")}
    backbone = build_backbone(cfg)
    base = module_bytes(backbone.transformer)
    adapters.add_adapter(backbone.transformer, "student", cfg.lora)
    loaded = {
        "transformer (shared base)": base,
        "adapter student": sum(p.numel() * p.element_size()
                               for p in adapters.adapter_parameters(backbone.transformer, "student")),
        "VAE": module_bytes(backbone.codec.vae),
        "T5 text encoder": module_bytes(backbone.text_encoder.model),
        "DINOv2": module_bytes(backbone.reference_encoder.dino.model),
        "VGGT": module_bytes(backbone.reference_encoder.vggt.model),
    }
    assert {name: h.bytes for name, h in counted.items()} == loaded
    # The paper's dtype policy, kept by the rehearsal: bf16 base and encoders, float32 LoRA factors and VAE.
    assert [counted[n].dtype for n in loaded] == ["bfloat16", "float32", "float32", "bfloat16", "bfloat16",
                                                  "bfloat16"]
    assert backbone.text_encoder.model.dtype == backbone.reference_encoder.dino.model.dtype == torch.bfloat16
    assert all(h.home == "cpu" and h.visits is None for h in counted.values())  # no accelerator: nothing moves
    assert device_totals(list(counted.values())) == {"cpu": sum(loaded.values())}
    # Variant A alone: one base and no adapter; plain 3DGS holds nothing.
    assert "adapter student" not in {h.component for h in restorer_holdings(cfg, ["baseline"], None, "cpu")}
    assert restorer_holdings(cfg, ["3dgs"], None, "cpu") == []


def test_offloaded_encoders_visit_the_accelerator_one_at_a_time(rehearsal_root, vggt_double):
    cfg = OmegaConf.to_object(rehearsal_config(rehearsal_root, "evaluate").backbone)
    assert cfg.offload_encoders  # the paper's policy (conf/backbone/cogvideox5b.yaml)
    holdings = restorer_holdings(cfg, METHODS, None, device="cuda")  # meta device: no GPU needed
    resident = [h for h in holdings if h.home == "cuda"]
    visitors = [h for h in holdings if h.visits == "cuda"]
    assert {h.component for h in visitors} == {"T5 text encoder", "DINOv2", "VGGT"}
    assert all(h.home == "cpu" for h in visitors)
    totals = device_totals(holdings)
    assert totals["cuda"] == sum(h.bytes for h in resident) + max(h.bytes for h in visitors)
    assert totals["cpu"] == sum(h.bytes for h in visitors)
    table = holdings_table(holdings)
    assert "T5 text encoder" in table and "on cuda only while it runs" in table and "peak per device" in table


def _paper_weights_configs(folder):
    """Published configurations of the paper's frozen components, as ``config.json`` files (no weights)."""
    from diffusers import AutoencoderKLCogVideoX
    from transformers import Blip2Config, Dinov2WithRegistersConfig, OPTConfig, T5Config

    T5Config(vocab_size=32128, d_model=4096, d_kv=64, d_ff=10240, num_layers=24, num_heads=64,
             feed_forward_proj="gated-gelu").save_pretrained(folder / "text_encoder")  # T5 v1.1 XXL
    Dinov2WithRegistersConfig(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, image_size=518,
                              patch_size=14).save_pretrained(folder / "dinov2-with-registers-large")
    with torch.device("meta"):
        AutoencoderKLCogVideoX().save_config(folder / "vae")  # diffusers' defaults are CogVideoX's VAE
    (folder / "VGGT-1B").mkdir()
    (folder / "VGGT-1B" / "config.json").write_text('{"embed_dim": 1024, "patch_size": 14}')
    opt = OPTConfig(hidden_size=2560, num_hidden_layers=32, ffn_dim=10240, num_attention_heads=32,
                    vocab_size=50272, word_embed_proj_dim=2560)  # OPT-2.7B
    Blip2Config(text_config=opt.to_dict()).save_pretrained(folder / "blip2-opt-2.7b")


def test_paper_figure_at_paper_shapes_on_the_meta_device(tmp_path, vggt_double):
    _paper_weights_configs(tmp_path)
    # The paper's backbone as users compose it (conf/backbone/cogvideox5b.yaml), its folders pointed here.
    cfg = OmegaConf.to_object(rehearsal_config(tmp_path, "evaluate", ("experiment=paper",
        "backbone.transformer.pretrained_path=null", f"backbone.codec.pretrained_path={tmp_path / 'vae'}",
        f"backbone.reference_encoder.dino_path={tmp_path / 'dinov2-with-registers-large'}",
        f"backbone.reference_encoder.vggt_path={tmp_path / 'VGGT-1B'}",
        f"backbone.text_encoder.pretrained_path={tmp_path / 'text_encoder'}",
        "backbone.text_encoder.tokenizer_path=null")).backbone)
    holdings = {h.component: h for h in restorer_holdings(
        cfg, METHODS, str(tmp_path / "blip2-opt-2.7b"), device="cuda")}
    training = training_component_bytes(cfg)
    assert holdings["transformer (shared base)"].bytes == training["transformer_base"]
    assert holdings["adapter student"].bytes == training["student_adapter"] == 4 * 66_060_288  # rank-32 LoRA
    # Published parameter counts (bf16 = 2 bytes each): T5-XXL encoder 4.76 B, DINOv2-L 304 M, BLIP-2 OPT-2.7B
    # 3.74 B; the VAE stays float32 (4 bytes).
    assert holdings["T5 text encoder"].bytes / 2 == pytest.approx(4.76e9, rel=0.01)
    assert holdings["DINOv2"].bytes / 2 == pytest.approx(3.04e8, rel=0.01)
    assert holdings["BLIP-2 captioner"].bytes / 2 == pytest.approx(3.74e9, rel=0.02)
    assert holdings["BLIP-2 captioner"].dtype == "bfloat16"
    assert holdings["VAE"].bytes / 4 == pytest.approx(2.16e8, rel=0.02)
    totals = device_totals(list(holdings.values()))
    # One 5B base + adapter + VAE resident, the largest encoder (T5) only while it encodes: well inside the
    # paper's 80 GB GPU before activations (two backbones with float32 encoders were about 70 GB).
    resident = sum(h.bytes for h in holdings.values() if h.home == "cuda")
    assert totals["cuda"] == resident + holdings["T5 text encoder"].bytes
    assert totals["cuda"] < 25 * GIB
