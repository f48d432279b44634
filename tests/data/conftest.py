"""Fixtures of the data tests: a tiny COLMAP scene, the tiny backbone and one prepared tiny cache."""

from __future__ import annotations

from pathlib import Path

import pytest
from scene_builders import tiny_configs, write_scene

from tracegs.data.preparation.driver import run_prepare
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.splat.cameras import Camera


@pytest.fixture
def colmap_scene(tmp_path: Path) -> tuple[Path, list[Camera]]:
    return write_scene(tmp_path / "scenes" / "ring")


@pytest.fixture(scope="session")
def backbone():
    return build_backbone(BackboneConfig())


@pytest.fixture(scope="session")
def prepared(tmp_path_factory, backbone):
    """(tmp dir, synthetic cfg, source cfg, prepare cfg, manifest path) of a cache built once per session."""
    tmp = tmp_path_factory.mktemp("prepared")
    synthetic, source, prepare = tiny_configs(tmp)
    manifest = run_prepare(prepare, source, backbone, synthetic, progress=False)
    return tmp, synthetic, source, prepare, manifest
