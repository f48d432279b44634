"""The rehearsal's world: the paper's weights tree (tiny random components) under one temporary root."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict
from paper_scenes import synthetic_scenes, write_dl3dv, write_mipnerf360, write_nerfbusters
from paper_weights import install_vggt_double, write_weights

from tracegs.cli.app import CONF_DIR, run_task
from tracegs.config.schema import register_configs


def rehearsal_config(root: Path, config_name: str = "train", overrides: tuple[str, ...] = ()):
    """``conf/<config_name>.yaml`` under ``experiment=rehearsal`` with every path below ``root``."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        return compose(config_name=config_name,
                       overrides=["experiment=rehearsal", f"paths.root_dir={root}", *overrides])


@contextlib.contextmanager
def rehearsal_job(root: Path, config_name: str, overrides: tuple[str, ...] = ()) -> Iterator[DictConfig]:
    """``rehearsal_config`` as the console script's job sees it: inside Hydra with the job's overrides known,
    so the run folders it names (run identity) are the ones that command line writes and reads."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        cfg = compose(config_name=config_name, return_hydra_config=True,
                      overrides=["experiment=rehearsal", f"paths.root_dir={root}", *overrides])
        HydraConfig.instance().set_config(cfg)
        try:
            with open_dict(cfg):
                del cfg["hydra"]
            yield cfg
        finally:
            HydraConfig.instance().cfg = None


def run_rehearsal_task(task, root: Path, config_name: str, overrides: tuple[str, ...] = ()):
    """Run ``task`` as its console script does (tracegs.cli.app.run_task: validation, seeding, the task), so
    each stage finds the products of the stages before it."""
    with rehearsal_job(root, config_name, overrides) as cfg:
        return run_task(task, cfg)


def rehearsal_run_dir(root: Path, config_name: str, overrides: tuple[str, ...] = (), key: str = "run_dir") -> Path:
    """The folder a rehearsal command line writes (``key``: ``run_dir`` or ``evaluation.out_dir``)."""
    with rehearsal_job(root, config_name, overrides) as cfg:
        return Path(str(OmegaConf.select(cfg, key)))


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
