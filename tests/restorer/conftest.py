"""Shared tiny restorer fixtures (embedded-scale backbone, seeded)."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig


@pytest.fixture
def backbone():
    torch.manual_seed(0)
    return build_backbone(BackboneConfig())


@pytest.fixture
def paper_backbone() -> BackboneConfig:
    """The paper's backbone exactly as users run it: conf/backbone/cogvideox5b.yaml, composed by Hydra."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=paper"])
    return OmegaConf.to_object(cfg.backbone)


@pytest.fixture
def make_inputs(backbone):
    """``make_inputs(batch, frames, seed)``: random model inputs at the backbone's latent / token shapes."""
    return lambda batch=2, frames=3, seed=0: random_inputs(backbone, batch, frames, seed)


def random_inputs(backbone, batch: int, frames: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t = backbone.cfg.transformer
    latent = (batch, frames, t.latent_channels, t.sample_height, t.sample_width)
    refs = (
        2
        * (48 // backbone.cfg.reference_encoder.patch_size)
        * (72 // backbone.cfg.reference_encoder.patch_size)
    )
    return dict(
        noisy=torch.randn(latent, generator=g),
        cond=torch.randn(latent, generator=g),
        timestep=torch.rand(batch, generator=g),
        text=torch.randn(batch, t.max_text_seq_length, t.text_embed_dim, generator=g),
        ref_2d=torch.randn(batch, refs, t.ref_2d_dim, generator=g),
        ref_3d=torch.randn(batch, refs, t.ref_3d_dim, generator=g),
    )
