"""One decorator turns a task function into a Hydra app with the project's conventions.

Every console script (`tracegs-prepare`, `-train`, `-deploy`, `-evaluate`, `-report`, `-demo`) is a
Hydra app over the same ``conf/`` tree and root schema, so ``-m`` sweeps, ``--cfg job`` and
``hydra/launcher=...`` work on each. The wrapper registers the schema, validates cross-field rules,
seeds everything, and turns the errors a user can fix into one line on stderr and exit code 2
(set ``TRACEGS_TRACEBACK=1`` to see the traceback instead).
"""

from __future__ import annotations

import functools
import importlib.resources
import os
import sys
from collections.abc import Callable
from typing import Any

import hydra
from omegaconf import DictConfig

from tracegs.cli.sweep import JobFailed, print_configs, sweeping
from tracegs.config.schema import register_configs
from tracegs.config.validate import validate

# The repository's conf/ folder, installed as the package tracegs.conf (pyproject.toml maps it), so an
# editable install and a wheel resolve it alike; TRACEGS_CONF points at another config tree if needed.
CONF_DIR = os.environ.get("TRACEGS_CONF", str(importlib.resources.files("tracegs.conf")))

# Errors caused by the user's input (config values, files on disk): reported in one line, no traceback.
USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, KeyError)


def hydra_app(config_name: str) -> Callable[[Callable[[DictConfig], Any]], Callable[[], Any]]:
    """Wrap ``task(cfg)`` as a Hydra main reading ``conf/<config_name>.yaml``."""

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[[], Any]:
        @functools.wraps(task)
        def run(cfg: DictConfig) -> Any:
            try:
                validate(cfg)
                import lightning

                lightning.seed_everything(cfg.seed, workers=True, verbose=False)
                return task(cfg)
            except USER_ERRORS as error:
                if os.environ.get("TRACEGS_TRACEBACK"):
                    raise
                message = error.args[0] if isinstance(error, KeyError) and error.args else error
                print(f"tracegs-{config_name}: error: {message}", file=sys.stderr)
                if sweeping():  # the other sweep points still run; SweepSummary lists the failures at the end
                    return JobFailed(str(message))
                sys.exit(2)

        register_configs()
        hydra_main = hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)(run)

        @functools.wraps(hydra_main)
        def main() -> Any:
            if print_configs(CONF_DIR, config_name, sys.argv[1:]):
                return None
            return hydra_main()

        return main

    return decorate
