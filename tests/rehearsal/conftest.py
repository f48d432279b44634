"""The rehearsal's world: the paper's weights tree (tiny random components) under one temporary root."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, open_dict
from paper_scenes import synthetic_scenes, write_dl3dv, write_mipnerf360, write_nerfbusters
from paper_weights import install_vggt_double, write_weights

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs


def rehearsal_config(root: Path, config_name: str = "train", overrides: tuple[str, ...] = ()):
    """``conf/<config_name>.yaml`` under ``experiment=rehearsal`` with every path below ``root``."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        return compose(config_name=config_name,
                       overrides=["experiment=rehearsal", f"paths.root_dir={root}", *overrides])


def run_rehearsal_task(task, root: Path, config_name: str, overrides: tuple[str, ...] = ()):
    """Run ``task`` as its console script would on ``rehearsal_config``'s command line: inside Hydra, with the
    job's overrides known, so each stage finds the products of the stages before it (run identity)."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        cfg = compose(config_name=config_name, return_hydra_config=True,
                      overrides=["experiment=rehearsal", f"paths.root_dir={root}", *overrides])
        HydraConfig.instance().set_config(cfg)
        try:
            with open_dict(cfg):
                del cfg["hydra"]
            return task(cfg)
        finally:
            HydraConfig.instance().cfg = None


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
