"""One runner for every chain of steps: ``tracegs-demo`` runs its steps in its own process, the replicated Table 3
(``tracegs-replicate``) as child commands, the Table 3 sweep (``launch/sweep_ablation.sh``) as one multirun per
step through a Hydra launcher (local or SLURM). The step lists are declared once (tracegs.pipeline.steps); a caller
only chooses how its steps execute (:class:`InProcess`, :class:`Commands`).

A step's settings are typed values (a number, a list, a path, None, a :class:`Sweep` of a multirun's values), and
one function writes them as Hydra overrides (:func:`override`): paths are quoted, since a folder the user chose
may hold ',', '=' or brackets, which unquoted are override syntax. A step may hand a product on: it names a key of
its own composed config (e.g. its cache's folder), and a later step takes that value for one of its keys.
"""

from __future__ import annotations

import logging
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import lightning
from hydra import compose
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from tracegs.config.overrides import with_overrides
from tracegs.config.tree import search_path_of
from tracegs.config.validate import validate
from tracegs.errors import TraceGSError

log = logging.getLogger("tracegs")

# A default for "no settings" (immutable, unlike a literal {}).
NO_SETTINGS: Mapping[str, Any] = MappingProxyType({})
# A string written as is: a name, a number-like token or one interpolation; anything else is quoted.
_PLAIN = re.compile(r"[\w.+/-]+|\$\{[\w.:,/-]+\}")


@dataclass(frozen=True)
class Sweep:
    """The values a multirun sweeps one key over (one job each)."""

    values: tuple[Any, ...]


def value_text(value: Any) -> str:
    """``value`` in Hydra's override grammar."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, Sweep):
        return ",".join(value_text(v) for v in value.values)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(value_text(v) for v in value) + "]"
    text = str(value)
    if _PLAIN.fullmatch(text):
        return text
    # Hydra's quoted strings: a quote is escaped, and so is each backslash run before a quote or the closing one;
    # any other backslash is literal.
    text = re.sub(r"(\\*)'", lambda m: m.group(1) * 2 + "\\'", text)
    return "'" + re.sub(r"(\\+)$", lambda m: m.group(1) * 2, text) + "'"


def override(key: str, value: Any) -> str:
    """One Hydra override setting ``key`` (a dotted key, or a group such as ``stage`` or ``hydra/launcher``)."""
    return f"{key}={value_text(value)}"


@dataclass(frozen=True)
class Step:
    """One command of a chain: the console script's module under ``tracegs.cli`` (and its ``conf/<app>.yaml``), its
    typed ``settings`` (key -> value, in order), the raw overrides it passes on from the user's command line
    (``passed``; the step's own settings win over them), and what the logs call it. ``hands`` names products for
    later steps (product name -> key of this step's composed config); ``takes`` fills keys from earlier steps'
    products (key -> product name, or ``name/relative`` for a path inside a handed folder)."""

    app: str
    settings: tuple[tuple[str, Any], ...]
    label: str
    passed: tuple[str, ...] = ()
    hands: Mapping[str, str] = field(default_factory=dict)
    takes: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def of(cls, app: str, label: str, *settings: Mapping[str, Any] | Sequence[tuple[str, Any]],
           **links: Mapping[str, str]) -> Step:
        """A step from settings given as mappings or pairs, later ones winning."""
        merged: dict[str, Any] = {}
        for part in settings:
            for key, value in (part.items() if isinstance(part, Mapping) else part):
                merged.pop(key, None)
                merged[key] = value
        return cls(app, tuple(merged.items()), label, **links)

    @property
    def overrides(self) -> tuple[str, ...]:
        """The step's command line: the user's overrides it passes on, then its own settings, which win (a held-out
        prepare prepares the test split whatever the user's command line says)."""
        return tuple(with_overrides(self.passed, [override(k, v) for k, v in self.settings]))

    @property
    def is_multirun(self) -> bool:
        return any(isinstance(v, Sweep) for _, v in self.settings)

    def with_settings(self, settings: Mapping[str, Any]) -> Step:
        kept = tuple((k, v) for k, v in self.settings if k not in settings)
        return replace(self, settings=kept + tuple(settings.items()))

    def passing(self, user: Sequence[str], leaving_out: Callable[[str], bool] = lambda _: False) -> Step:
        """The step with the user's overrides passed on (those ``leaving_out`` picks left out)."""
        return replace(self, passed=tuple(o for o in user if not leaving_out(o)))

    def jobs(self) -> list[Step]:
        """The single runs a multirun step expands to, one per swept value (as Hydra's basic sweeper orders them)."""
        swept = [(k, v.values) for k, v in self.settings if isinstance(v, Sweep)]
        if not swept:
            return [self]
        (key, values), *more = swept
        if more:
            raise ValueError(f"step '{self.label}' sweeps {len(swept)} keys; jobs() expands one")
        return [replace(self.with_settings({key: value}), label=f"{self.label} {value}") for value in values]


def composed(config_name: str, overrides: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` under ``overrides`` in the open Hydra context, which it keeps as its
    ``command_line``, and the context's search path as its ``config_search_path``."""
    cfg = compose(config_name=config_name, overrides=list(overrides))
    cfg.command_line = list(overrides)
    cfg.config_search_path = search_path_of(GlobalHydra.instance().config_loader())
    return cfg


def compose_run(cfg: DictConfig, config_name: str, extra: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` with the command-line overrides of ``cfg`` and ``extra`` (which wins),
    validated: the config of a step this process runs, as its own command would compose it."""
    cfg = composed(config_name, with_overrides(cfg.command_line, extra))
    validate(cfg)
    return cfg


class InProcess:
    """Runs each step's task in this process on a config composed from ``cfg``'s command line and the step's
    overrides (:func:`compose_run`)."""

    def __init__(self, cfg: DictConfig, tasks: Mapping[str, Callable[[DictConfig], Any]]) -> None:
        self.cfg, self.tasks = cfg, tasks
        self.last: DictConfig | None = None  # the config of the step that ran last, whose products run_steps reads

    def command(self, step: Step) -> list[str]:
        return [f"tracegs-{step.app}", *step.overrides]

    def run(self, step: Step) -> None:
        if step.is_multirun:
            raise ValueError(f"step '{step.label}' is a multirun; run its jobs() in this process")
        step_cfg = compose_run(self.cfg, step.app, step.overrides)
        lightning.seed_everything(step_cfg.seed, workers=True, verbose=False)
        self.tasks[step.app](step_cfg)
        self.last = step_cfg

    def product(self, step: Step, key: str) -> Any:
        """Read from the config ``step`` just ran on (run_steps asks right after running it)."""
        return OmegaConf.select(self.last, key)


class Commands:
    """Runs each step as the console command a user would type, in a child process of this Python. A multirun
    step (or every step, with ``every_step_multirun``) runs through ``hydra/launcher=<launcher>`` (on SLURM the
    submitit launcher waits for its jobs, so each step sees the one before finished)."""

    def __init__(self, launcher: str = "local", every_step_multirun: bool = False) -> None:
        self.launcher, self.every_step_multirun = launcher, every_step_multirun

    def command(self, step: Step) -> list[str]:
        script = Path(sys.executable).with_name(f"tracegs-{step.app}")
        program = [str(script)] if script.is_file() else [sys.executable, "-m", f"tracegs.cli.{step.app}"]
        if step.is_multirun or self.every_step_multirun:
            return [*program, "-m", override("hydra/launcher", self.launcher), *step.overrides]
        return [*program, *step.overrides]

    def run(self, step: Step) -> None:
        command = self.command(step)
        if subprocess.run(command, check=False).returncode != 0:
            raise TraceGSError(f"step '{step.label}'", "failed (its error is printed above)",
                               f"rerun it alone: {shlex.join(command)}")

    def product(self, step: Step, key: str) -> Any:
        """Read from the step's config composed here: its child process made the product there."""
        return OmegaConf.select(composed(step.app, step.overrides), key)


def _product_name(spec: str) -> str:
    return spec.partition("/")[0]


def _taken(products: Mapping[str, Any], spec: str) -> Any:
    """The value a ``takes`` entry names: a handed product (``name``), or a path inside it (``name/relative``)."""
    name, _, inside = spec.partition("/")
    value = products.get(name, f"<{name}>")
    return f"{value}/{inside}" if inside else value


def run_steps(steps: Sequence[Step], executor: InProcess | Commands, runner: str,
              dry_run: bool = False) -> dict[str, float]:
    """Run ``steps`` in order with ``executor``, handing each product on to the steps that take it; the seconds
    each step took, by label. Stops at the first step that fails (its error says how to rerun it)."""
    taken = {_product_name(spec) for step in steps for spec in step.takes.values()}
    products: dict[str, Any] = {}
    timings: dict[str, float] = {}
    for index, step in enumerate(steps, 1):
        missing = sorted({_product_name(spec) for spec in step.takes.values()} - set(products))
        if missing and not dry_run:
            raise ValueError(f"step '{step.label}' takes {missing}, which no earlier step hands on")
        step = step.with_settings({key: _taken(products, spec) for key, spec in step.takes.items()})
        log.info("[%s %d/%d] %s: %s", runner, index, len(steps), step.label, shlex.join(executor.command(step)))
        if dry_run:
            continue
        start = time.perf_counter()
        executor.run(step)
        timings[step.label] = round(time.perf_counter() - start, 1)
        products.update({name: executor.product(step, key) for name, key in step.hands.items() if name in taken})
    return timings
