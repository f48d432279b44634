"""`launch/paper_scope.sh --dry-run`: every sbatch line of the paper's scope, each depending on the one before,
its memory, CPUs, GPUs, requeue lead and shards those of the measured rules (tracegs.cluster.jobs)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from tracegs.cluster.jobs import JOB_KINDS, measured_iteration, memory_gb, signal_lead_seconds

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import paper_scope  # noqa: E402

H200 = REPO / "docs" / "gpu_check" / "h200-2026-11-26.json"
KINDS = {"gpu-check": "prepare", "prepare-shard0": "prepare", "prepare": "prepare", "stage1": "train",
         "stage2": "train", "fig6-held-out": "prepare", "fig6": "report"}


@pytest.fixture(scope="module")
def lines():
    return paper_scope.main(["--dry-run", "--partition", "gpu", "--account", "lab", "--measured", str(H200)])


def option(line: str, name: str) -> str | None:
    found = re.search(rf" --{name}=(\S+)", line)
    return found.group(1) if found else None


def test_the_chain_depends_step_by_step(lines):
    labels = [option(line, "job-name").split("-", 2)[2] for line in lines]
    assert labels[:5] == ["gpu-check", "prepare-shard0", "prepare", "stage1", "stage2"]
    assert labels[-2:] == ["fig6-held-out", "fig6"]
    assert any(label.startswith("evaluate") for label in labels) and "Tables-12-on-dl3dv" in labels
    assert option(lines[0], "dependency") is None
    for number, line in enumerate(lines[1:], 2):
        assert option(line, "dependency") == f"afterok:$JOB_{number - 1}", line
    assert all(option(line, "partition") == "gpu" and option(line, "account") == "lab" for line in lines)
    assert all(" --requeue" in line for line in lines)  # every job resumes after a requeue
    assert ".venv/bin/tracegs-weights --check" in lines[0]


def test_each_line_is_sized_by_the_measured_rules(lines):
    step_s, _ = measured_iteration(H200)
    for line in lines:
        label = option(line, "job-name").split("-", 2)[2]
        kind = KINDS.get(label) or ("evaluate" if label.startswith("evaluate") else "report")
        tasks = int(option(line, "ntasks-per-node"))
        assert option(line, "mem") == f"{memory_gb(kind, tasks)}G", line
        assert int(option(line, "cpus-per-task")) == JOB_KINDS[kind].cpus
        hours, minutes, _ = option(line, "time").split(":")
        assert int(hours) * 60 + int(minutes) <= 48 * 60, line  # no job beyond the limit
        if kind == "train":
            assert tasks == 4 and option(line, "gpus-per-node") == "4" and "launch/slurm_ddp.sbatch" in line
            assert option(line, "signal") == f"USR2@{signal_lead_seconds(step_s * 2.5)}"  # the assumed A100 factor
        else:
            assert tasks == 1 and option(line, "gpus-per-node") == "1"
            assert option(line, "signal") == f"B:USR2@{paper_scope.PREPARE_LEAD_S}"
            assert "launch/requeue_on_signal.sh .venv/bin/tracegs-" in line or "requeue_on_signal.sh sh -c" in line


def test_the_prepare_shards_fill_the_array(lines):
    shards = int(re.search(r"data\.prepare\.num_shards=(\d+)", lines[1]).group(1))
    assert shards > 1 and "data.prepare.shard_index=0" in lines[1]
    assert option(lines[2], "array") == f"0-{shards - 2}"
    assert "data.prepare.shard_index=$((SLURM_ARRAY_TASK_ID + 1))" in lines[2]


def test_the_job_shell_reads_hydra_values_back_word_for_word(lines):
    import shlex

    (wrap,) = [word.removeprefix("--wrap=") for word in shlex.split(lines[-1]) if word.startswith("--wrap=")]
    words = shlex.split(wrap)
    assert words[:2] == ["launch/requeue_on_signal.sh", ".venv/bin/tracegs-report"]
    assert "evaluation.held_out_cache=${data.prepare.cache_dir}" in words and "report.kind=per_step" in words
