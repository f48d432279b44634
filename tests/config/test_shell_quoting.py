"""The advice for an override Hydra's grammar refuses (tracegs.cli.precheck): the override as it must be typed in
bash, checked by typing it in bash, then through a real entry point with a folder named as people name them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra.core.override_parser.overrides_parser import OverridesParser

from tracegs.cli.precheck import shell_override

RESTORE = Path(sys.executable).with_name("tracegs-restore")
FOLDERS = ["/data/Mes photos d'été", "/data/a,b=c [1]", "/data/it's $HOME `x` \"q\"!", "/data/trailing\\",
           "'/data/quoted by hand'"]


def through_bash(word: str) -> str:
    """What bash hands a program for ``word`` typed on its command line."""
    return subprocess.run(["bash", "-c", f"printf %s {word}"], capture_output=True, text=True, check=True).stdout


@pytest.mark.parametrize("folder", FOLDERS)
def test_the_advised_override_reaches_hydra_as_the_folder(folder):
    (parsed,) = OverridesParser.create().parse_overrides([through_bash(shell_override(f"capture.path={folder}"))])
    expected = folder[1:-1] if folder.startswith("'") else folder
    assert parsed.key_or_group == "capture.path" and parsed.value() == expected


def test_a_folder_with_an_apostrophe_spaces_and_accents_is_refused_with_advice_that_works(tmp_path):
    folder = tmp_path / "Mes photos d'été"
    folder.mkdir()
    refused = subprocess.run([str(RESTORE), f"capture.path={folder}", f"paths.root_dir={tmp_path}"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    (line,) = [line for line in refused.stderr.splitlines() if line.strip()]
    advice = line.split("in bash: ", 1)[1]
    followed = subprocess.run(["bash", "-c", f"{RESTORE} {advice} paths.root_dir={tmp_path} --cfg job"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert followed.returncode == 0, followed.stderr[-2000:]
    assert yaml.safe_load(followed.stdout)["capture"]["path"] == str(folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == [folder.name]  # neither command wrote anything
