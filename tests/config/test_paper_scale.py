"""Paper-scale settings that `experiment=paper` must carry itself (found by rehearsing the paper scale)."""

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


def test_paper_fits_use_the_reference_3dgs_optimiser(paper):
    """Sec. 4.1 fits 3DGS for 30k iterations with the reference optimiser (Kerbl et al. 2023), not the
    embedded CPU schedule (densify 50-450 of 600, reset every 200, 10x the position rate, 8k cap)."""
    fit = paper.data.prepare.fit
    dens = fit.densification
    assert (fit.iterations, fit.lr_means, fit.lr_means_final, fit.sh_degree_interval) == (30000, 1.6e-4, 1.6e-6, 1000)
    schedule = (dens.refine_start_iter, dens.refine_stop_iter, dens.refine_every, dens.reset_every)
    assert schedule[:3] == (500, 15000, 100)
    assert dens.grow_grad2d == 2e-4
    assert dens.max_gaussians is None  # the reference optimiser has no cap
