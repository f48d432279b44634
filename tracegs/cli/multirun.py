"""Multirun bookkeeping: a job that fails on bad input does not stop the multirun, and the multirun ends with a
summary of every job (a Hydra callback, registered in each primary config under ``hydra.callbacks``).

Hydra's basic launcher stops at the first job that exits, and reports a failed job only as a traceback
after the batch; a sweep over the ablation grid should instead run every point it can and say at the end
which ones failed and why.
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass
from typing import Any

from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from tracegs.cli.failures import USER_ERRORS, exit_with_one_line
from tracegs.cluster.jobs import measured_iteration, require_lead
from tracegs.config.validate import validate
from tracegs.errors import ConfigError


@dataclass
class JobFailed:
    """What a multirun job returns when it stopped on bad input (already reported on stderr in one line)."""

    message: str


def in_multirun() -> bool:
    """Whether this job is one point of a multirun launched in this process (Hydra's basic launcher).

    Jobs on other machines (the SLURM launcher) still exit with status 2: each is its own SLURM job, so
    the others run anyway, and the launching process sees the failure."""
    if not HydraConfig.initialized():
        return False
    hydra_cfg = HydraConfig.get()
    return hydra_cfg.mode == RunMode.MULTIRUN and hydra_cfg.launcher._target_.endswith(".BasicLauncher")


class MultirunSummary(Callback):
    """Collects each job's outcome in the launching process; prints them after the multirun, exit 2 on failures.

    Jobs that run in other processes (the SLURM launcher) report in their own logs instead.
    """

    def __init__(self) -> None:
        self.outcomes: list[tuple[str, str]] = []

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        if config.hydra.launcher._target_.endswith(".SlurmLauncher"):
            try:
                require_slurm_launch(config)
            except USER_ERRORS as error:
                exit_with_one_line(config.hydra.help.app_name.removeprefix("tracegs-"), error)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        overrides = " ".join(job_return.overrides or []) or "(no overrides)"
        if job_return.status == JobStatus.FAILED:
            outcome = f"failed: {job_return._return_value}"
        elif isinstance(job_return.return_value, JobFailed):
            outcome = f"failed: {job_return.return_value.message}"
        else:
            outcome = "ok"
        self.outcomes.append((overrides, outcome))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if not self.outcomes:
            return
        failed = [o for o in self.outcomes if o[1] != "ok"]
        app = config.hydra.help.app_name
        succeeded = len(self.outcomes) - len(failed)
        print(f"{app}: {succeeded} of {len(self.outcomes)} multirun jobs succeeded", file=sys.stderr)
        for number, (overrides, outcome) in enumerate(self.outcomes):
            print(f"  #{number} {overrides}: {outcome}", file=sys.stderr)
        if failed:
            sys.exit(2)


def require_slurm_launch(config: DictConfig) -> None:
    """What submitting to SLURM needs, checked before the first job is submitted: the account and partition it is
    billed to, SLURM's commands on this machine, and a requeue signal early enough for the measured iteration."""
    launcher = config.hydra.launcher
    unset = [f"hydra.launcher.{key}" for key in ("partition", "account") if not launcher.get(key)]
    if unset:
        raise ConfigError(" and ".join(unset), "required at hydra/launcher=slurm (the cluster bills and places "
                                               "each job by them); set them on the command line")
    if shutil.which("sbatch") is None:
        raise ConfigError("hydra/launcher=slurm", "no SLURM on this machine (sbatch is not on PATH): submit from "
                                                  "the cluster's login node, or run here with hydra/launcher=local")
    gpu_check = config.trainer.cluster.get("gpu_check")
    if gpu_check is not None:
        seconds, origin = measured_iteration(gpu_check)
        require_lead(launcher.signal_delay_s, seconds, origin, "hydra.launcher.signal_delay_s")


def print_configs(config_dir: str, config_name: str, argv: list[str]) -> bool:
    """``--cfg`` where Hydra refuses or crashes: with ``-m`` (one YAML document per multirun job, expanded by
    Hydra's own basic sweeper) and ``--cfg hydra|all --resolve`` (Hydra prints its node without the job
    config that run_dir and the launcher's resources interpolate). Returns False when Hydra can do it.
    """
    flags = [a for a in argv if a in ("-c", "--cfg")]
    if not flags:
        return False
    position = argv.index(flags[0]) + 1
    which = argv[position] if position < len(argv) and argv[position] in ("job", "hydra", "all") else "job"
    resolve = "--resolve" in argv
    multirun = bool({"-m", "--multirun"} & set(argv))
    if not multirun and not (resolve and which != "job"):
        return False
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    jobs = [overrides]
    if multirun:
        parsed = OverridesParser.create().parse_overrides(overrides)
        jobs = [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]
    with initialize_config_dir(config_dir=config_dir, version_base="1.3"):
        configs = [compose(config_name=config_name, overrides=job, return_hydra_config=which != "job") for job in jobs]
        if which == "job":
            refuse_invalid(config_name, configs)  # every job's config is valid before any is printed
        for number, (job, cfg) in enumerate(zip(jobs, configs)):
            shown = resolve_leniently(cfg) if resolve else OmegaConf.to_container(cfg)
            if multirun:
                print(f"# job #{number}: {' '.join(job)}")
            print(OmegaConf.to_yaml(shown["hydra"] if which == "hydra" else shown), end="---\n" if multirun else "")
    return True


def refuse_invalid(app: str, configs: list[DictConfig]) -> None:
    """One line on stderr and exit code 2 for the first config that fails validation."""
    for cfg in configs:
        try:
            validate(cfg)
        except USER_ERRORS as error:
            exit_with_one_line(app, error)


def resolve_leniently(node: DictConfig | ListConfig) -> Any:
    """The node as plain containers with every interpolation resolved that can be; Hydra's runtime fields
    (hydra.job.num, ...) exist only inside a launched job, so values built on them stay interpolations."""
    keys = range(len(node)) if isinstance(node, ListConfig) else list(node.keys())
    resolved = [] if isinstance(node, ListConfig) else {}
    for key in keys:
        child = node._get_node(key)
        if isinstance(child, (DictConfig, ListConfig)) and not child._is_interpolation():
            value = resolve_leniently(child)
        else:
            try:
                value = node[key]
                if isinstance(value, (DictConfig, ListConfig)):
                    value = OmegaConf.to_container(value, resolve=True)
            except OmegaConfBaseException:
                value = child._value()
        if isinstance(resolved, list):
            resolved.append(value)
        else:
            resolved[key] = value
    return resolved
