"""A SLURM launch refused in one line, exit 2, before anything is submitted: without partition and account, on a
machine without SLURM, or with a requeue signal too late for the measured iteration; and the lead-time and shard
rules it applies."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tracegs.cluster.jobs import (
    REQUEUE_SECONDS,
    SAVE_SECONDS,
    STEP_MARGIN,
    measured_iteration,
    require_lead,
    shard_count,
    signal_lead_seconds,
)
from tracegs.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
H200 = REPO / "docs" / "gpu_check" / "h200-2026-11-26.json"


def launch(tmp_path: Path, *overrides: str, path: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": path or os.environ["PATH"]}
    return subprocess.run([sys.executable, "-c", "from tracegs.cli.train import main; main()", "-m",
                           "hydra/launcher=slurm", "experiment=rehearsal", f"paths.root_dir={tmp_path}", *overrides],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)


def fake_sbatch(tmp_path: Path) -> str:
    """A PATH whose sbatch records that it ran (the launch must refuse before it does)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text(f"#!/bin/sh\ntouch {tmp_path / 'submitted'}\n")
    (bin_dir / "sbatch").chmod(0o755)
    return f"{bin_dir}{os.pathsep}{os.environ['PATH']}"


def test_the_lead_covers_the_measured_h200_iteration():
    seconds, origin = measured_iteration(H200)
    assert seconds == pytest.approx(112.39, abs=0.01) and "NVIDIA H200" in origin
    assert signal_lead_seconds(seconds) == 231 == -(-(seconds * STEP_MARGIN + SAVE_SECONDS + REQUEUE_SECONDS) // 1)
    require_lead(600, seconds, origin, "hydra.launcher.signal_delay_s")  # the launcher's default fits
    with pytest.raises(ConfigError, match="at least 231"):
        require_lead(120, seconds, origin, "hydra.launcher.signal_delay_s")  # the old default did not


def test_no_shard_exceeds_the_limit():
    assert shard_count(112, 3600, 48 * 3600) == 3  # 38 scenes of an hour fit in 80% of 48 h
    assert shard_count(112, 3 * 3600, 48 * 3600) == 10  # 12 scenes of 3 h per shard
    with pytest.raises(ConfigError, match="no shard fits"):
        shard_count(4, 40 * 3600, 48 * 3600)


def test_slurm_without_partition_and_account_is_refused(tmp_path):
    run = launch(tmp_path)
    assert run.returncode == 2, run.stderr[-2000:]
    assert run.stderr.strip().splitlines() == [
        "tracegs-train: error: config field 'hydra.launcher.partition and hydra.launcher.account': required at "
        "hydra/launcher=slurm (the cluster bills and places each job by them); set them on the command line"]


def test_slurm_on_a_machine_without_it_is_refused(tmp_path):
    run = launch(tmp_path, "hydra.launcher.partition=gpu", "hydra.launcher.account=lab",
                 path="/usr/bin:/bin")
    assert run.returncode == 2, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "sbatch is not on PATH" in lines[0], run.stderr[-2000:]


def test_a_lead_shorter_than_the_measured_iteration_is_refused(tmp_path):
    run = launch(tmp_path, "hydra.launcher.partition=gpu", "hydra.launcher.account=lab",
                 "hydra.launcher.signal_delay_s=120", f"trainer.cluster.gpu_check={H200}", path=fake_sbatch(tmp_path))
    assert run.returncode == 2, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "'hydra.launcher.signal_delay_s'" in lines[0] and "at least 231" in lines[0], lines
    assert not (tmp_path / "submitted").exists()


@pytest.mark.parametrize(("trainer", "kind", "tasks"), [("ddp", "train", 4), ("gpu", "prepare", 1)])
def test_the_trainers_ask_slurm_for_the_measured_memory(trainer, kind, tasks):
    from hydra import compose, initialize_config_dir

    from tracegs.cluster.jobs import memory_gb
    from tracegs.config.schema import register_configs
    from tracegs.location import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cluster = compose(config_name="train", overrides=["experiment=paper", f"trainer={trainer}"]).trainer.cluster
    assert cluster.mem_gb == memory_gb(kind, tasks) >= memory_gb("prepare")
