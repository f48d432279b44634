"""The rehearsal's world: the paper's weights tree (tiny random components) under one temporary root."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf
from paper_scenes import synthetic_scenes, write_dl3dv, write_mipnerf360, write_nerfbusters
from paper_weights import install_vggt_double, write_weights
from support.rehearsal import rehearsal_config


@pytest.fixture(scope="session")
def rehearsal_root(tmp_path_factory) -> Path:
    """A launch directory holding ``weights/`` as the README documents it."""
    root = tmp_path_factory.mktemp("rehearsal")
    backbone = OmegaConf.to_object(rehearsal_config(root).backbone)
    write_weights(backbone, root / "weights")
    return root


@pytest.fixture
def vggt_double(monkeypatch):
    install_vggt_double(monkeypatch)


@pytest.fixture(scope="session")
def paper_data(rehearsal_root) -> dict[str, Path]:
    """The synthetic benchmark (one training, one benchmark scene) in each paper dataset's layout under
    ``<root>/data``; the DL3DV root is where ``experiment=rehearsal`` looks."""
    cfg = rehearsal_config(rehearsal_root)
    data = Path(cfg.paths.data_dir)
    train, benchmark = synthetic_scenes(data / "generated", [0], [100], cfg.data.source.height,
                                        cfg.data.source.width, num_views=24)
    return {
        "dl3dv": write_dl3dv(data, train, benchmark),
        "mipnerf360": write_mipnerf360(data / "with_splits", benchmark, split_files=True),
        "mipnerf360_no_splits": write_mipnerf360(data / "without_splits", benchmark, split_files=False),
        "nerfbusters": write_nerfbusters(data, benchmark),
    }
