"""Hydra's records of a command (``.hydra/`` in its run folder: the composed config, Hydra's own and the overrides)
are written by the entry point once the command succeeded, not by Hydra before it runs (tracegs.cli.app)."""

from __future__ import annotations

from pathlib import Path

import yaml
from scene_builders import write_scene
from support.inputs import TINY_PREPARE


def test_a_finished_command_records_how_it_was_run(tmp_path: Path, entry_point):
    scenes = tmp_path / "scenes"
    write_scene(scenes / "ring", n=12)
    overrides = [*TINY_PREPARE, f"data.source.root={scenes}", f"paths.root_dir={tmp_path}"]
    result = entry_point("prepare", overrides, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    (records,) = tmp_path.rglob(".hydra")
    assert sorted(p.name for p in records.iterdir()) == ["config.yaml", "hydra.yaml", "overrides.yaml"]
    assert yaml.safe_load((records / "overrides.yaml").read_text()) == overrides
    assert yaml.safe_load((records / "config.yaml").read_text())["task"] == "prepare"
    hydra = yaml.safe_load((records / "hydra.yaml").read_text())["hydra"]
    assert Path(hydra["runtime"]["output_dir"]) == records.parent
