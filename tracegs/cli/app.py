"""One decorator turns a task function into a Hydra app with the project's conventions.

Every console script (`tracegs-prepare`, `-train`, `-deploy`, `-evaluate`, `-report`, `-demo`) is a
Hydra app over the same ``conf/`` tree and root schema, so ``-m`` multiruns, ``--cfg job`` and
``hydra/launcher=...`` work on each. The wrapper registers the schema, validates cross-field rules,
seeds everything, and turns the errors a user can fix into one line on stderr and exit code 2
(set ``TRACEGS_TRACEBACK=1`` to see the traceback instead).
"""

from __future__ import annotations

import copy
import functools
import gc
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
import lightning
import torch
from diffusers.utils import logging as diffusers_logging
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from tracegs.cli.failures import exit_with_one_line, memory_failure, report_one_line, user_error
from tracegs.cli.multirun import JobFailed, in_multirun, print_configs
from tracegs.cli.precheck import refuse_bad_command_line
from tracegs.cli.relaunch import one_job_argv, overrides_for_launched_ranks
from tracegs.config.schema import register_configs
from tracegs.config.tree import search_path_of
from tracegs.config.validate import validate, validate_names
from tracegs.console import LogBookmark, quiet_library_notices
from tracegs.errors import ConfigError, TraceGSError, out_of_memory, require_writable_dir, writable
from tracegs.io import atomic_write
from tracegs.location import CONF_DIR
from tracegs.pipeline.records import migrate_older_folders
from tracegs.processes import stops_quietly


def log_libraries_through_hydra() -> None:
    """Send Lightning's and diffusers' messages to Hydra's handlers (console on stdout, the run's log file).

    Lightning and diffusers give their loggers their own stderr handler: their notices would then mix with
    the one-line error on stderr and never reach the log file.
    """
    diffusers_logging.disable_default_handler()
    diffusers_logging.enable_propagation()
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in [h for h in logger.handlers if type(h) is logging.StreamHandler]:
            logger.removeHandler(handler)
        logger.propagate = True


class MigrateOlderFolders(Callback):
    """Hydra callback: the one step of a command that renames the product folders an older version named
    (tracegs.pipeline.records.migrate_older_folders), before Hydra or the task resolves a folder; once for a
    multirun, whose jobs share the root. ``--cfg`` never runs it: printing a config writes nothing."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        migrate_older_folders(config)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        migrate_older_folders(config)


class OutputsWritable(Callback):
    """Hydra callback: check the names that make up the run (or sweep) folder are plain names and the folder is a
    writable directory, before Hydra writes into it.

    Hydra creates the folder and its log file before the task function runs, so the wrapper below
    would only see Hydra's own traceback for an output path that is a file or read-only. A single run whose
    folder already exists where nothing can be written (a read-only copy of a finished root) is let through
    with Hydra's log file off (the log goes to the console): a step with nothing to do writes
    nothing, and one that would write refuses in one line naming the file.
    """

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_dir = Path(config.hydra.run.dir)
        if run_dir.is_dir() and not writable(run_dir):
            with open_dict(config):
                config.hydra.job_logging = CONSOLE_LOGGING
            return
        self._check(config, "run", "hydra.run.dir (run_dir)", kwargs.get("config_name", "run"))

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, "sweep", "hydra.sweep.dir", kwargs.get("config_name", "run"))

    @staticmethod
    def _check(config: DictConfig, mode: str, field: str, app: str) -> None:
        try:
            validate_names(config)  # names become folders of the run path: one with '..' would leave the root
            require_writable_dir(config.hydra[mode].dir, field)
        except (TraceGSError, ConfigError) as error:
            if os.environ.get("TRACEGS_TRACEBACK"):
                raise
            exit_with_one_line(app, error)


# Hydra's job logging without its file handler: the console alone (a read-only run folder).
CONSOLE_LOGGING = {
    "version": 1,
    "formatters": {"simple": {"format": "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"}},
    "handlers": {"console": {"class": "logging.StreamHandler", "formatter": "simple", "stream": "ext://sys.stdout"}},
    "root": {"level": "INFO", "handlers": ["console"]},
    "disable_existing_loggers": False,
}


# What a run folder holds before it holds a product: Hydra's record of the command, the log, empty logger folders.
_ATTEMPT_RECORDS = (".hydra", "csv", "tensorboard")


_STARTED = time.time()


def remove_attempt_records(cfg: DictConfig) -> None:
    """Remove the run folder of this single run if this command created it and it holds only records of the
    attempt: a refused command writes nothing, and a retry starts from a clean folder (its logger at version_0).

    Created by this command: every file in it is younger than this process. (Hydra names the folder from the
    command line only once the job starts, so its path is read here, from the job's runtime config.) The
    folders above it that are left empty go too, up to the root."""
    if in_multirun() or not HydraConfig.initialized():
        return
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    files = [p for p in run_dir.rglob("*") if not p.is_dir()]
    if all((f.relative_to(run_dir).parts[0] in _ATTEMPT_RECORDS or f.suffix == ".log")
           and f.stat().st_mtime >= _STARTED for f in files):
        logging.shutdown()  # the log file's handler lets go of it first
        shutil.rmtree(run_dir, ignore_errors=True)
        root = Path(OmegaConf.select(cfg, "paths.root_dir", default=".")).absolute()
        for parent in run_dir.parents:
            if parent == root or root not in parent.parents:
                break
            try:
                parent.rmdir()
            except OSError:  # not empty: something else lives there
                break


# Where Hydra's records of the command go in its run folder (Hydra's own default for hydra.output_subdir).
HYDRA_RECORDS = ".hydra"


def write_hydra_records(task_cfg: DictConfig, log: LogBookmark) -> None:
    """Hydra's records of this command (``config.yaml``, ``hydra.yaml``, ``overrides.yaml``, as Hydra writes them)
    in the run folder's ``.hydra/``, once the command succeeded: a refused or interrupted command writes none, and
    one that made nothing (its log left as it was, tracegs.console.LogBookmark) keeps those of the command that
    made the products, so a rerun on a copy of a finished root changes no byte. A rank that Lightning launched
    writes none (its launcher's are the job's), nor does a command in a folder nothing can be written to."""
    if not HydraConfig.initialized() or int(os.environ.get("LOCAL_RANK", "0")) > 0:
        return
    hydra_cfg = HydraConfig.instance().cfg
    run_dir = Path(hydra_cfg.hydra.runtime.output_dir)
    folder = run_dir / HYDRA_RECORDS
    if (folder.is_dir() and log.kept()) or not writable(run_dir):
        return
    folder.mkdir(exist_ok=True)
    for name, node in (("config.yaml", task_cfg), ("hydra.yaml", hydra_cfg),
                       ("overrides.yaml", hydra_cfg.hydra.overrides.task)):
        with atomic_write(folder / name) as tmp:
            tmp.write_text(OmegaConf.to_yaml(node), encoding="utf-8")


def exit_at_once(code: int) -> None:
    """Exit with ``code``, leaving the objects made so far out of the interpreter's teardown collection: a stopped
    command has nothing left to write, and collecting every object the libraries made takes seconds (4 to 9 s
    after Ctrl-C during a two-worker prepare on two loaded cores, measured). The exit handlers still run
    (multiprocessing's releases the worker pool's semaphores)."""
    gc.freeze()
    sys.exit(code)


def run_task(task: Callable[[DictConfig], Any], cfg: DictConfig) -> Any:
    """What every entry point does with its composed config: validate the cross-field rules, route the
    libraries' messages through Hydra's logging, seed everything from ``cfg.seed``, run ``task``."""
    if HydraConfig.initialized():
        # The one place the command line is read: an in-process runner composes its steps from the typed copy.
        cfg.command_line = list(HydraConfig.get().overrides.task)
        cfg.config_search_path = search_path_of(GlobalHydra.instance().config_loader())
    validate(cfg)
    log_libraries_through_hydra()
    quiet_library_notices()
    lightning.seed_everything(cfg.seed, workers=True, verbose=False)
    threads = OmegaConf.select(cfg, "trainer.cpu_threads")
    if threads is not None:  # every command, not only training: concurrent runs on shared cores otherwise spin
        torch.set_num_threads(threads)
    return task(cfg)


def hydra_app(config_name: str) -> Callable[[Callable[[DictConfig], Any]], Callable[[], Any]]:
    """Wrap ``task(cfg)`` as a Hydra main reading ``conf/<config_name>.yaml``."""

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[[], Any]:
        @functools.wraps(task)
        def run(cfg: DictConfig) -> Any:
            given, log = copy.deepcopy(cfg), LogBookmark()
            try:
                # SIGTERM stops the command as Ctrl-C does, in one line (during training's fit Lightning's own
                # handling takes over: a checkpoint after the step in flight, tracegs.training.checkpoints).
                with stops_quietly(tracebacks=bool(os.environ.get("TRACEGS_TRACEBACK"))):
                    if in_multirun():
                        with overrides_for_launched_ranks():
                            result = run_task(task, cfg)
                    else:
                        result = run_task(task, cfg)
                write_hydra_records(given, log)
                return result
            except KeyboardInterrupt:
                # Every product is written whole or not at all, so an interrupted command has nothing to undo:
                # one line instead of the tracebacks of every frame it was in, and the shell's code for SIGINT.
                report_one_line(config_name, "interrupted (Ctrl-C); the same command goes on from the last "
                                             "finished product")
                remove_attempt_records(cfg)
                exit_at_once(130)
            except Exception as raised:  # user_error tells what the user can fix (memory included) from a bug
                error = user_error(raised, cfg)
                if error is None or os.environ.get("TRACEGS_TRACEBACK"):
                    raise
                message = report_one_line(config_name, error)
                if in_multirun():  # the other multirun jobs still run; MultirunSummary lists the failures at the end
                    return JobFailed(message)
                remove_attempt_records(cfg)
                sys.exit(2)

        register_configs()
        hydra_main = hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)(run)

        @functools.wraps(hydra_main)
        def main() -> Any:
            if not os.environ.get("TRACEGS_TRACEBACK"):
                refuse_bad_command_line(config_name, CONF_DIR, config_name, sys.argv[1:])  # before Hydra writes
            if print_configs(CONF_DIR, config_name, sys.argv[1:]):
                return None
            sys.argv[1:] = one_job_argv(sys.argv[1:])  # a rank launched for one job of a multirun
            try:
                return hydra_main()
            except Exception as error:  # memory that ran out before the task, or in Hydra reporting an error
                if out_of_memory(error) is None or os.environ.get("TRACEGS_TRACEBACK"):
                    raise
                exit_with_one_line(config_name, memory_failure(error))

        return main

    return decorate
