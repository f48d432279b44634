"""Prepare and deployment read one trajectory config in every experiment and dataset."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs


@pytest.mark.parametrize("experiment", ["embedded", "paper"])
@pytest.mark.parametrize("data", ["synthetic", "dl3dv", "mipnerf360", "nerfbusters"])
def test_prepare_renders_clips_along_the_deployment_trajectory_config(experiment, data):
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="prepare", overrides=[f"experiment={experiment}", f"data={data}",
                                                        "deploy.trajectory.ellipse_scales=[0.9,0.5]"])
    prepare = OmegaConf.to_container(cfg.data.prepare.trajectory, resolve=True)
    assert prepare == OmegaConf.to_container(cfg.deploy.trajectory, resolve=True)
    assert prepare["ellipse_scales"] == [0.9, 0.5]
    assert prepare["frames_per_clip"] == cfg.data.prepare.frames_per_clip
