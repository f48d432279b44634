"""Fixtures of the splatting tests (the scenes they build live in support/scenes.py)."""

from __future__ import annotations

import pytest
from support.scenes import ring_cameras

from tracegs.splat.cameras import Camera


@pytest.fixture
def camera() -> Camera:
    return ring_cameras(1)[0]
