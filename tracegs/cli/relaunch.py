"""A rank that Lightning launched for one job of a Hydra multirun runs that job only.

Lightning starts each further local rank with the launching command line plus ``hydra.run.dir=<the job's
folder>`` (lightning.fabric.strategies.launchers.subprocess_script._hydra_subprocess_cmd). Under ``-m`` that
command line is the whole sweep, so the new rank would run every sweep point itself. The job's own overrides,
which Hydra wrote to ``<run dir>/.hydra/overrides.yaml`` before the job started, replace the sweep.
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

MULTIRUN_FLAGS = ("-m", "--multirun")
# What Lightning appends for the new rank (kept as is).
LAUNCH_KEYS = ("hydra.run.dir=", "hydra.job.name=", "hydra.output_subdir=")


def one_job_argv(argv: list[str], environ=os.environ) -> list[str]:
    """``argv`` (without the program) for this process: unchanged unless it is a rank Lightning launched
    (LOCAL_RANK > 0) from a multirun, then the job's overrides and Lightning's additions."""
    if int(environ.get("LOCAL_RANK", "0")) == 0 or not set(argv) & set(MULTIRUN_FLAGS):
        return argv
    launch = [arg for arg in argv if arg.startswith(LAUNCH_KEYS)]
    run_dir = next((arg.split("=", 1)[1].strip('"') for arg in launch if arg.startswith("hydra.run.dir=")), None)
    if run_dir is None:
        return argv
    overrides = Path(run_dir) / ".hydra" / "overrides.yaml"
    if not overrides.is_file():
        raise FileNotFoundError(f"{overrides}: the job's overrides, which this launched rank runs, are missing")
    return [*yaml.safe_load(overrides.read_text()), *launch]
