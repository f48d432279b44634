"""Inputs the entry points must refuse, and how a refusal is checked: exit code 2, one line, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs

# A one-scene prepare at the smallest sizes (one student set, 16-iteration fits): seconds, not minutes.
TINY_PREPARE = ["data=custom", "data.source.height=32", "data.source.width=48",
                "data.prepare.pseudo_target=dense", "data.prepare.student_views=[3]", "data.prepare.dense_views=[null]",
                "data.prepare.student_snapshots=[8]", "data.prepare.fit.iterations=16",
                "data.prepare.fit.snapshot_iters=[8,16]", "data.datamodule.student_views=[3]",
                "data.datamodule.student_snapshots=[8]", "data.prepare.workers=1", "data.prepare.clips_per_scene=1"]


# tracegs-restore at the smallest sizes, plain 3DGS only (no restorer weights needed).
TINY_RESTORE = ["evaluation.methods=[3dgs]", "experiment.frame_height=32", "experiment.frame_width=48",
                "data.prepare.fit.iterations=40", "data.prepare.fit.snapshot_iters=[10,20,40]",
                "deploy.total_iters=40", "deploy.repair_iters=[10,25]", "evaluation.progress=false", "capture.size=48"]


def tiny_backbone_config():
    """The backbone the entry points build by default (conf/backbone/tiny.yaml)."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return OmegaConf.to_object(compose(config_name="train").backbone)


def files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def assert_refused(result, app: str, expected: str, written: set[Path]) -> None:
    """Exit code 2, one line on stderr naming ``expected``, and no file ``written`` (the run folder the command
    made for itself, Hydra's record and the log in it, removed again)."""
    lines = result.stderr_lines()
    assert result.returncode == 2, result.stderr[-3000:]
    assert len(lines) == 1, result.stderr[-3000:]
    assert lines[0].startswith(f"tracegs-{app}: error: ") and expected in lines[0], lines[0]
    assert written == set()


def overwrite_tensor_bytes(shard: Path, key: str = "latent/target") -> None:
    """Change a few bytes of one tensor in place to other finite values, as a damaged disk or a careless edit
    would: the file stays a valid safetensors file with plausible numbers."""
    data = bytearray(shard.read_bytes())
    length = int.from_bytes(data[:8], "little")
    begin, _ = json.loads(data[8:8 + length])[key]["data_offsets"]
    start = 8 + length + begin
    values = np.frombuffer(bytes(data[start:start + 8]), dtype=np.float16) + np.float16(0.5)
    data[start:start + 8] = values.tobytes()
    shard.write_bytes(bytes(data))
