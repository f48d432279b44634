"""The package installs from a wheel and finds its Hydra configs there (not in the source tree)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]


def _run(command: list, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in command], capture_output=True, text=True, check=True, timeout=300,
                          **kwargs)


@pytest.mark.slow  # builds a wheel and a fresh venv (~14 s)
def test_wheel_installs_in_a_fresh_venv_and_composes(tmp_path):
    # Build from a copy of the sources, so the wheel cannot lean on the checkout and no build/ folder
    # lands in it; --no-build-isolation uses this venv's setuptools (nothing is downloaded).
    source = tmp_path / "source"
    for part in ("tracegs", "conf"):
        shutil.copytree(REPO / part, source / part, ignore=shutil.ignore_patterns("__pycache__"))
    for part in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / part, source / part)
    wheels = tmp_path / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", wheels, source])
    (wheel,) = wheels.glob("tracegs-*.whl")

    # A fresh venv gets only the wheel; its dependencies (torch 2.13.0 included) are this venv's,
    # appended to its path by a .pth file, so pip never resolves or fetches a dependency.
    env_dir = tmp_path / "fresh"
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", "--no-index", wheel])
    fresh_site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    (fresh_site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    conf_dir = _run([python, "-c", "from tracegs.cli.app import CONF_DIR; print(CONF_DIR)"], cwd=tmp_path).stdout
    assert Path(conf_dir.strip()).is_relative_to(fresh_site)
    out = _run([env_dir / "bin" / "tracegs-train", "experiment=paper", "--cfg", "job"], cwd=tmp_path).stdout
    cfg = OmegaConf.create(out)
    assert cfg.task == "train" and cfg.experiment.name == "paper"
    assert cfg.backbone.name == "cogvideox_5b"


def test_every_subpackage_ships():
    """pyproject.toml lists packages explicitly (to map conf/ into tracegs.conf): a new subpackage must be added."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "tracegs").rglob("__init__.py")}
    assert on_disk | {"tracegs.conf"} == listed
