"""Fixtures of the data tests: a tiny COLMAP scene, the tiny backbone and one prepared tiny cache."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest
import torch
from scene_builders import tiny_configs, write_scene

from tracegs.data.prepare import run_prepare
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.splat.cameras import Camera


@contextlib.contextmanager
def one_thread():
    """The data tests move tiny tensors: one intra-op thread is fastest, and on a shared 2-core machine
    multi-threaded kernels oversubscribe the cores (measured 5-10x slower). Restored afterwards, so the
    other packages' tests keep their setting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    with one_thread():
        yield


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
    with one_thread():  # session fixtures are set up before the module-scoped autouse one
        manifest = run_prepare(prepare, source, backbone, synthetic, progress=False)
    return tmp, synthetic, source, prepare, manifest
