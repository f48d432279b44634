"""`--help` of every console script: what it does, every config group with its options, examples, one screen."""

from __future__ import annotations

import contextlib
import importlib
import io
import sys
from pathlib import Path
from unittest import mock

import pytest

from tracegs.cli.app import CONF_DIR

SCREEN_LINES = 40
SCREEN_COLUMNS = 120
CONF = Path(CONF_DIR)
# Every config group outside hydra/, found on disk so that a new group must show up in the help.
GROUPS = sorted(p.name for p in CONF.iterdir() if p.is_dir() and p.name not in ("hydra", "__pycache__"))
# The scripts that compose no config (plain argparse), so their help has no config groups to list.
NO_CONFIG = {"tracegs-view": "serves a finished run folder as it is",
             "tracegs-weights": "fetches and verifies files, before any config is run"}


def console_scripts() -> dict[str, str]:
    """Script name -> "module:function", as pyproject.toml declares them."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    return tomllib.loads(pyproject.read_text())["project"]["scripts"]


def entry_points() -> list[str]:
    return sorted(console_scripts())


@pytest.fixture(scope="module")
def help_pages() -> dict[str, str]:
    """Each console script's --help, run in this process through the script's own entry point."""
    pages = {}
    for name in entry_points():
        module, function = console_scripts()[name].split(":")
        main = getattr(importlib.import_module(module), function)
        with mock.patch.object(sys, "argv", [name, "--help"]), \
                contextlib.redirect_stdout(io.StringIO()) as out, pytest.raises(SystemExit) as done:
            main()
        assert done.value.code == 0, f"{name} --help exited with {done.value.code}"
        pages[name] = out.getvalue()
    return pages


def test_every_entry_point_has_a_help_page(help_pages):
    assert set(help_pages) >= {f"tracegs-{n}" for n in ("prepare", "train", "deploy", "evaluate", "report", "demo")}


@pytest.mark.parametrize("name", entry_points())
def test_help_fits_one_screen_and_names_the_groups(help_pages, name):
    page = help_pages[name]
    lines = page.rstrip("\n").splitlines()
    assert len(lines) <= SCREEN_LINES, f"{name} --help has {len(lines)} lines"
    assert max(len(line) for line in lines) <= SCREEN_COLUMNS
    assert lines[0].startswith(f"usage: {name} ")
    if name not in NO_CONFIG:
        listed = {line.split(":")[0] for line in lines if ": " in line}
        assert set(GROUPS) <= listed, f"groups missing from {name} --help: {sorted(set(GROUPS) - listed)}"
        assert "experiment: embedded, embedded_gt_targets, embedded_onestep, paper, rehearsal, replicate" in page
    # Two examples of this very command; the config dump stays behind --cfg.
    examples = page.split("Examples:")[1].splitlines()
    assert sum(line.strip().startswith(name) for line in examples) >= 2
    assert "lambda_ret" not in page and "powered by Hydra" not in page
