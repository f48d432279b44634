"""Upstream lookup: where the product of an earlier run lies, worked out from the typed config of the run that
needs it.

Nothing is composed again from a command line. The earlier run's config is a projection of this one, and its
folder follows from that by the run-identity rule (tracegs.config.identity), which reads the fields each product
declares:

- **its stage.** A stage's own sections (``stage``, ``optimizer``) hold what the ``stage`` group option sets
  (conf/stage/<stage>.yaml: budgets and rates from ``experiment.<stage>_*``, the run folder) on the schema's
  defaults. A training command's own overrides of them describe that command's stage only, so an earlier stage is
  looked up at its option's values; an evaluation's describe the student it loads (its default stage).
- **its variant.** A and the Stage-1 adapter are shared by every Table 3 variant: they are looked up with the
  default variant's sections. A student or evaluation of another variant takes that variant's sections
  (the stage table's ``variant_sections``, tracegs.stages; the variant's declaration, tracegs.pipeline.variants).
- **its data.** A product of this run's dataset shares its data section. The restorers trained on another one
  (``training_data``, when this run evaluates another dataset or restores a capture of the user's own) and an
  evaluation of another dataset (Table 3's out-of-domain columns) are found by the run records beside the
  products (tracegs.pipeline.records): the one finished product there made on that dataset with this run's every
  other setting.
"""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from tracegs.config.identity import scoped_values
from tracegs.config.schema import AUTO, Task
from tracegs.config.tree import ConfigTree
from tracegs.errors import ConfigError
from tracegs.pipeline.records import CONTENT, RUN_RECORD
from tracegs.pipeline.variants import variant_sections
from tracegs.stages import stage_table

log = logging.getLogger("tracegs")


def section(node: DictConfig) -> Any:
    """The dataclass instance behind a structured config node (interpolations resolved)."""
    return OmegaConf.to_object(node)


def _set_sections(cfg: DictConfig, source: DictConfig, names: Iterable[str]) -> None:
    for name in names:
        cfg[name] = copy.deepcopy(source[name])


def as_variant(cfg: DictConfig, variant: str) -> DictConfig:
    """A copy of ``cfg`` run for Table 3 variant ``variant``: its sections in place of this config's."""
    projected = copy.deepcopy(cfg)
    if variant != cfg.ablation.name:
        _set_sections(projected, variant_sections(variant, ConfigTree.of(cfg)), stage_table().variant_sections)
    return projected


def upstream_config(cfg: DictConfig, kind: str, variant: str | None = None) -> DictConfig:
    """The config of the earlier ``kind`` run (a trained stage or "evaluate"; a stage trained per variant and an
    evaluation of ``variant``, default this config's) whose product ``cfg`` needs, on this config's dataset: a projection of
    ``cfg`` (see the module docstring). ``cfg``'s own folders and artifacts must not be pinned yet."""
    table = stage_table()
    trained = kind in table.names()
    if trained and not table.stage(kind).per_variant:
        projected = copy.deepcopy(cfg)
        _set_sections(projected, variant_sections(None, ConfigTree.of(cfg)), table.shared_by_variants)
    else:
        projected = as_variant(cfg, variant or cfg.ablation.name)
    if trained:
        option = ConfigTree.of(cfg).option("stage", kind)  # conf/stage/<kind>.yaml as written
        if cfg.stage.name != kind:  # another stage's overrides of the stage sections are that stage's own
            _set_sections(projected, OmegaConf.structured(OmegaConf.get_type(cfg)), table.stage_sections)
            projected.merge_with(option)
        projected.run_dir = option["run_dir"]
    return projected


def product_folder(cfg: DictConfig, kind: str, variant: str | None = None, data: str | None = None) -> Path:
    """The folder of the earlier ``kind`` run whose product ``cfg`` needs (:func:`upstream_config`), on dataset
    ``data``: default the training data (``training_data``) for a trained product, this run's for an evaluation.
    On another dataset than this run's, the run record there that matches (:func:`recorded_folder`)."""
    trained = kind in stage_table().names()  # looked up on the training data
    data = data or (cfg.training_data if trained else cfg.data.name)
    projected = upstream_config(cfg, kind, variant)
    folder = Path(str(projected.run_dir if trained else projected.evaluation.out_dir))
    # tracegs-restore's data section describes the user's capture, whatever data option it starts from.
    if data == cfg.data.name and not (trained and cfg.task == Task.restore):
        return folder
    return recorded_folder(projected, kind, data, folder.parent)


def _compared(values: dict[str, Any]) -> dict[str, Any]:
    """The record keys a product on another dataset is compared by: not that dataset's own section, nor the earlier
    products' paths (their contents are recorded apart), nor those contents."""
    return {key: value for key, value in values.items() if not key.startswith(("data.", "artifacts.", CONTENT))}


def recorded_folder(projected: DictConfig, kind: str, data: str, parent: Path) -> Path:
    """The folder under ``parent`` whose run record is a finished ``kind`` run on dataset ``data`` with every other
    setting of ``projected`` (a config of this run's dataset). None made: a folder that does not exist, named so
    that the error of whatever loads its product says what is missing; several: refused in one line."""
    expected = _compared(scoped_values(projected, kind))
    matches = []
    for record in sorted(parent.glob(f"*/{RUN_RECORD}")):
        try:
            values = json.loads(record.read_text())
        except (OSError, json.JSONDecodeError) as error:
            log.warning("%s: unreadable run record, its folder is not considered (%s)", record, error)
            continue
        if values.get("data.name") == data and _compared(values) == expected:
            matches.append(record.parent)
    if len(matches) > 1:
        table = stage_table()
        field = f"artifacts.{table.stage(kind).artifact}" if kind in table.names() else "data"
        raise ConfigError(field, f"{len(matches)} {kind} runs on {data} match this run's settings "
                                 f"({', '.join(m.name for m in matches)} under {parent}); name the one to use")
    return matches[0] if matches else parent / f"none-on-{data}-with-these-settings"




def locate_artifacts(cfg: DictConfig, needed: Sequence[str]) -> None:
    """Replace each needed "auto" artifact by the product of the earlier run :func:`product_folder` finds.

    Every product is found from the configuration as given, and the run's own folders are resolved and kept
    before any artifact is filled in, so they stay named by it too."""
    producers = {artifact: stage_table().producer(artifact) for artifact in needed if cfg.artifacts[artifact] == AUTO}
    found = {artifact: product_folder(cfg, stage.product) / stage.folder for artifact, stage in producers.items()}
    for key in ("run_dir", "evaluation.out_dir"):
        OmegaConf.update(cfg, key, str(OmegaConf.select(cfg, key)))
    for artifact, path in found.items():
        cfg.artifacts[artifact] = str(path)
