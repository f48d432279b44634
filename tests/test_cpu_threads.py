"""``trainer.cpu_threads`` holds for every command, not only training: two runs sharing the cores with torch's
default threads each spin in OpenMP barriers (a held-out report ran five times slower)."""

from __future__ import annotations

import pytest
import torch
from hydra import compose

from tracegs.cli.app import run_task

pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


@pytest.mark.parametrize("config_name", ["report", "prepare", "evaluate"])
def test_every_command_runs_with_the_configured_threads(config_name):
    before = torch.get_num_threads()
    try:
        threads = run_task(lambda cfg: torch.get_num_threads(),
                           compose(config_name=config_name, overrides=[f"trainer.cpu_threads={before + 1}"]))
    finally:
        torch.set_num_threads(before)
    assert threads == before + 1
