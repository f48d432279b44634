"""Two-process training inside a Hydra multirun: a launched rank runs its job only, and the launching process
releases its ranks after each job so the next job launches its own."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import lightning as L
import pytest
import torch
import torch.distributed as dist
from lightning.pytorch.demos.boring_classes import BoringModel
from support.tasks import SMALLEST

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
    excepthook = sys.excepthook
    with one_job_of_processes():
        # what Lightning's launcher does in the launching process
        os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT="29500", NODE_RANK="0", LOCAL_RANK="0", WORLD_SIZE="1")
        dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
        assert sys.excepthook is not excepthook  # torch's rank-prefixing wrapper
    assert not dist.is_initialized()
    assert not {"MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE"} & set(os.environ)
    assert sys.excepthook is excepthook  # else each job of a multirun adds another "[rank0]: " to every line


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


# Run as a script: sys.argv[1:] are the training overrides (Lightning re-launches this script with them for rank
# 1); the launching process then prepares with worker processes, with the overrides in $PREPARE_ARGS.
TRAIN_THEN_PREPARE = '''
import json, os, sys
import torch.distributed as dist
from hydra.core.global_hydra import GlobalHydra
from tracegs.cli import prepare, train

if __name__ == "__main__":  # not in the prepare's spawned workers, which import this script as __mp_main__
    excepthook = sys.excepthook
    train.main()
    if "LOCAL_RANK" in os.environ:  # rank 1: its job is the training
        sys.exit(0)
    assert not dist.is_initialized() and sys.excepthook is excepthook, "the training left its process group behind"
    GlobalHydra.instance().clear()
    sys.argv = [sys.argv[0], *json.loads(os.environ["PREPARE_ARGS"])]
    prepare.main()
'''


@pytest.mark.slow
def test_two_process_training_then_a_prepare_with_workers_in_one_process(tmp_path, entry_point):
    """A sweep-like process: A trained on two gloo ranks, then a prepare whose worker processes receive
    tensors from this process (torch shares them through file descriptors): nothing the distributed run left
    behind stops the pool."""
    root = tmp_path / "root"
    root.mkdir()
    common = [f"paths.root_dir={root}", *SMALLEST]
    assert entry_point("prepare", common, root).returncode == 0
    script = tmp_path / "train_then_prepare.py"
    script.write_text(TRAIN_THEN_PREPARE)
    prepare_args = [*common, "data.prepare.split=val", "data.prepare.workers=2"]
    run = subprocess.run([sys.executable, str(script), *common, "stage=baseline", "trainer=ddp_sim"], cwd=root,
                         env={**os.environ, "PREPARE_ARGS": json.dumps(prepare_args), "TRACEGS_TRACEBACK": "1"},
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "Starting with 2 processes" in run.stdout + run.stderr
    assert list(root.glob("data/cache/synthetic-tiny-val-*/**/*.safetensors"))
