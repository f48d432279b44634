"""Two-process training inside a Hydra multirun: a launched rank runs its job only, and the launching process
releases its ranks after each job so the next job launches its own."""

from __future__ import annotations

import json
import os

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.demos.boring_classes import BoringModel

from tracegs.cli.relaunch import JOB_OVERRIDES, one_job_argv
from tracegs.training.strategy import one_job_of_processes

SWEEP = ["-m", "hydra/launcher=local", "stage=stage2", "ablation=B,C,F"]
LIGHTNING = ['hydra.run.dir="/runs/F"', "hydra.job.name=train_ddp_process_1", "hydra.output_subdir=null"]


def test_a_rank_launched_for_one_sweep_job_runs_that_job_only():
    job = ["hydra/launcher=local", "stage=stage2", "ablation=F"]
    launched = {"LOCAL_RANK": "1", JOB_OVERRIDES: json.dumps(job)}
    assert one_job_argv([*SWEEP, *LIGHTNING], launched) == [*job, *LIGHTNING]
    # the launching process itself, a rank of a single run, and a rank of a run that set no overrides: unchanged
    assert one_job_argv(SWEEP, {}) == SWEEP
    assert one_job_argv(["stage=stage2", *LIGHTNING], launched) == ["stage=stage2", *LIGHTNING]
    assert one_job_argv([*SWEEP, *LIGHTNING], {"LOCAL_RANK": "1"}) == [*SWEEP, *LIGHTNING]


def clear_launch_env(monkeypatch) -> None:
    for key in ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE", "OMP_NUM_THREADS"):
        monkeypatch.delenv(key, raising=False)


def test_the_launching_process_releases_its_ranks_after_a_job(tmp_path, monkeypatch):
    clear_launch_env(monkeypatch)
    with one_job_of_processes():
        # what Lightning's launcher does in the launching process
        os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT="29500", NODE_RANK="0", LOCAL_RANK="0", WORLD_SIZE="1")
        dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
    assert not dist.is_initialized()
    assert not {"MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE"} & set(os.environ)


def test_a_job_leaves_the_thread_count_it_found(monkeypatch):
    """Lightning's DDP launcher sets OMP_NUM_THREADS and torch's intra-op threads to cores / processes; left
    behind, the next job of a multirun in this process would compute with another count (other float bits)."""
    clear_launch_env(monkeypatch)
    threads = torch.get_num_threads()
    with one_job_of_processes():
        trainer = L.Trainer(accelerator="cpu", devices=1, strategy="ddp", max_steps=1, logger=False,
                            enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
        trainer.fit(BoringModel())
        assert "OMP_NUM_THREADS" in os.environ  # the launcher's setting, in force for the job
    assert torch.get_num_threads() == threads and "OMP_NUM_THREADS" not in os.environ
    assert not dist.is_initialized()
