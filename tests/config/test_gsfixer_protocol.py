"""Where the paper says "same as GSFixer", the paper-scale configuration follows GSFixer's released code
(GVCLab/GSFixer, ``Reconstruction/``). Each test names the file and line of their code the value follows."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs


@pytest.fixture(scope="module")
def paper():
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        yield compose(config_name="prepare", overrides=["experiment=paper"])


def test_opacity_reset_follows_gsfixers_mipnerf360_script(paper):
    """train_mipnerf360_sparse_view_recon_per_scene.py l. 49: ``--opacity_reset_interval 3100`` (the paper states
    no interval)."""
    assert paper.data.prepare.fit.densification.reset_every == 3100
