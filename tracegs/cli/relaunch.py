"""A rank that Lightning launched for one job of a Hydra multirun runs that job only.

Lightning starts each further local rank with the launching command line plus ``hydra.run.dir=...``,
``hydra.job.name=...`` and ``hydra.output_subdir=null``
(lightning.fabric.strategies.launchers.subprocess_script._hydra_subprocess_cmd) and a copy of the launching
process's environment. Under ``-m`` that command line is the whole multirun, so the new rank would run every
job of it itself. The launching job therefore puts its own overrides in the environment, and a launched rank runs
those instead of the multirun.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator

from hydra.core.hydra_config import HydraConfig

JOB_OVERRIDES = "TRACEGS_JOB_OVERRIDES"
MULTIRUN_FLAGS = ("-m", "--multirun")
LAUNCH_KEYS = ("hydra.run.dir=", "hydra.job.name=", "hydra.output_subdir=")  # Lightning's additions


@contextlib.contextmanager
def overrides_for_launched_ranks() -> Iterator[None]:
    """During one job of a multirun: its overrides in the environment the ranks it launches inherit."""
    os.environ[JOB_OVERRIDES] = json.dumps(list(HydraConfig.get().overrides.task))
    try:
        yield
    finally:
        os.environ.pop(JOB_OVERRIDES, None)


def one_job_argv(argv: list[str], environ=os.environ) -> list[str]:
    """``argv`` (without the program) for this process: unchanged unless it is a rank launched (LOCAL_RANK > 0)
    from a multirun job, then that job's overrides and Lightning's additions."""
    if int(environ.get("LOCAL_RANK", "0")) == 0 or not set(argv) & set(MULTIRUN_FLAGS) or JOB_OVERRIDES not in environ:
        return argv
    return [*json.loads(environ[JOB_OVERRIDES]), *(arg for arg in argv if arg.startswith(LAUNCH_KEYS))]
