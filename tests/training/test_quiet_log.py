"""What a stage prints: none of Lightning's advertisements or known harmless notices, every warning a user can act
on. The stage runs in its own process, so the test reads what a user's terminal shows (stdout and stderr)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import tracegs

TESTS = Path(__file__).resolve().parents[1]

# Two steps of the baseline on a random cache, through train_stage, Lightning's Trainer and the DataModule. The
# logging interval (50 steps) is longer than the epoch (2 batches): Lightning's hint to lower it is a warning
# about the user's own setting, and must still show.
STAGE = """
import dataclasses, sys
from pathlib import Path
from support.training_runs import config, write_cache
from tracegs.training.run import train_stage
tmp = Path(sys.argv[1])
cfg = config(tmp, write_cache(tmp / "cache"), "baseline", 2, "baseline")
train_stage(dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, log_every_n_steps=50)))
"""


def test_a_stage_prints_no_library_noise_and_every_actionable_warning(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(tracegs.__file__).parents[1]), str(TESTS)])}
    env.pop("PYTHONWARNINGS", None)
    run = subprocess.run([sys.executable, "-c", STAGE, str(tmp_path)], env=env, capture_output=True, text=True,
                         timeout=300)
    printed = run.stdout + run.stderr
    assert run.returncode == 0, printed
    assert (tmp_path / "baseline" / "baseline_transformer").is_dir()
    for noise in ("Tip:", "litlogger", "litmodels", "val_dataloader", "LeafSpec", "_pytree"):
        assert noise not in printed, printed
    assert "smaller than the logging interval Trainer(log_every_n_steps=50)" in printed, printed
