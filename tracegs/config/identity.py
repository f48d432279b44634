"""Run identity: a run's folder is named by the settings that determine its product.

Every product (a paired-clip cache, a trained restorer or adapter, an evaluation) depends on a known
part of the configuration: the fields that declare they change it (tracegs.products, next to each field of
the config dataclasses). The folder a run writes to is ``seed<k>-<digest>`` under a path of typed values
(experiment, stage, variant; a cache's dataset, backbone and split), the digest a hash of those fields' values
after interpolation: a function of the typed config alone, never of how the command line was spelt. So two runs
share a folder exactly when they would produce the same thing, a changed hyperparameter never resumes or
overwrites another run, and a later stage finds the product it needs by computing the earlier stage's folder
with the same rule (``tracegs.pipeline.upstream``); the folder's ``config.yaml`` and ``run_identity.json`` say
what it holds.

Fields that change how a run executes but not what it produces (paths, logging, progress bars,
parallelism, sharding, checkpoint cadence) are declared ``execution()`` and never part of an identity.

A product is named by the scenes it read (the scene lists declare their split): a trained restorer (A, Stage 1, Stage 2) and the training split's
cache by the training scenes, never by the test or validation lists; a cache of another split by that split's
scenes; an evaluation adds its own test scenes to the identity of the restorers it loads. The restorers are
trained on ``training_data`` (a ``data`` option the experiment chooses), so an evaluation of another dataset
(``data=mipnerf360``) finds the students of the experiment's training data (tracegs.pipeline.upstream).

One root ``seed`` drives every stochastic part: each part's own ``seed`` field is derived from it with
:func:`derive_seed` under the part's stream name, so streams differ between parts and between seeds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf

from tracegs.content import capture_digest, names_and_bytes_digest, root_relative
from tracegs.data.config import (
    PseudoTarget,
    Split,
    clip_target,
    fits_variant_teacher,
    is_procedural,
    with_variant_teacher,
)
from tracegs.products import BASELINE, PREPARE, Declaration, declarations
from tracegs.restorer.config import sections_not_in_cache
from tracegs.stages import stage_table

DIGEST_CHARS = 8

# The name the root schema is registered under in Hydra's ConfigStore (conf/command.yaml lists it first).
SCHEMA_NAME = "tracegs_schema"
# A capture of the user's own is identified by its content, not by where it lies: a folder by its images and
# reconstruction (its photos, when structure-from-motion makes the reconstruction), a video by its bytes.
CAPTURE_KEYS = ("capture.path", "capture.video")

def derive_seed(root_seed: int, stream: str) -> int:
    """The seed of one stochastic part: a stable 31-bit hash of (root seed, stream name)."""
    digest = hashlib.sha256(f"{int(root_seed)}:{stream}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def _leaves(holder: DictConfig, key: str, path: str, skip: frozenset[str]) -> Iterable[tuple[str, Any]]:
    """(dotted key, resolved value) of every leaf under ``holder[key]``, skipping excluded keys *before*
    resolving them (an excluded key may interpolate the run's own folder, which would recurse)."""
    if path in skip:
        return
    child = holder._get_node(key)
    if isinstance(child, DictConfig) and not child._is_none() and not child._is_interpolation():
        for sub in child.keys():
            yield from _leaves(child, str(sub), f"{path}.{sub}", skip)
        return
    value = holder[key]
    if isinstance(value, (DictConfig, ListConfig)):
        value = OmegaConf.to_container(value, resolve=True)
    yield path, value


def _declared(cfg: DictConfig) -> dict[str, Declaration]:
    """The field declarations of the schema ``cfg`` was composed from (tracegs.products); for an untyped config
    (a run's ``config.yaml`` written from a plain copy), those of the schema registered in Hydra's ConfigStore
    (tracegs.config.schema.register_configs)."""
    schema = OmegaConf.get_type(cfg)
    if not dataclasses.is_dataclass(schema):
        schema = OmegaConf.get_type(ConfigStore.instance().load(f"{SCHEMA_NAME}.yaml").node)
    return declarations(schema)


def read_fields(cfg: DictConfig, kind: str, split: str | None = None, unmade: Sequence[str] = ()) -> frozenset[str]:
    """The dotted paths of the fields whose values a ``kind`` run's product depends on, as the fields declare
    them (tracegs.products): a cache (of ``split``) reads the scene lists of its split only, and none of the
    backbone sections in ``unmade``. Inputs handed in by path are known by content instead (``_handed_in``)."""
    product = stage_table().product(kind, "run kind")
    unmade = tuple(f"backbone.{section}" for section in unmade)
    return frozenset(
        path for path, declared in _declared(cfg).items()
        if product in declared.products and declared.content is None
        and not (product == PREPARE and declared.split not in (None, split))
        and not any(path == section or path.startswith(f"{section}.") for section in unmade))


def _read(cfg: DictConfig, kind: str, split: str | None = None) -> frozenset[str]:
    """``read_fields`` of a ``kind`` run under ``cfg``: a cache is made with the backbone sections its
    pseudo-targets need only. A train split's cache whose pseudo-targets come from variant A as this framework
    trains it (``data.prepare.pseudo_target_weights`` interpolating the located A) reads A's settings too, so a
    changed A is a new cache, never stale targets: every field A reads except the sections each command's stage
    option sets, whose values for A come from the experiment section it reads."""
    if kind != "prepare":
        return read_fields(cfg, kind)
    target = clip_target(split, OmegaConf.select(cfg, "data.prepare.pseudo_target"), is_procedural(cfg.data.source))
    fields = read_fields(cfg, kind, split, sections_not_in_cache(target))
    if Split(split) != Split.train or target != PseudoTarget.restorer or not _generator_is_located(cfg):
        return fields
    # The sections a command's stage option sets (conf/stage/<stage>.yaml) from the experiment's values: variant
    # A's are those values, which the experiment section holds whatever stage the command runs.
    table = stage_table()
    option_sections = (*table.stage_sections, *table.option_also_sets)
    own_stage = tuple(f"{section}." for section in option_sections)
    return fields | frozenset(path for path in read_fields(cfg, BASELINE.value)
                              if path not in option_sections and not path.startswith(own_stage))


def _generator_is_located(cfg: DictConfig) -> bool:
    """Whether the pseudo-target generator is the product of an earlier run located by its identity (an
    interpolation of ``artifacts.baseline_weights``) rather than handed in by path or the backbone's own weights."""
    node = cfg.data.prepare._get_node("pseudo_target_weights")
    return node is not None and node._is_interpolation()


def scoped_values(cfg: DictConfig, kind: str) -> dict[str, Any]:
    """The flattened, resolved values that determine the product of a ``kind`` run.

    A path inside the run's root is kept relative to it, so the same root reached through another spelling, or
    copied or moved, is the same run; a capture handed in is known by its content (tracegs.content)."""
    split = OmegaConf.select(cfg, "data.prepare.split") if kind == "prepare" else None
    return _scoped_values(cfg, kind, _read(cfg, kind, split))


def _scoped_values(cfg: DictConfig, kind: str, read: frozenset[str]) -> dict[str, Any]:
    skip = frozenset(_declared(cfg)) - read
    values: dict[str, Any] = {}
    for key in sorted(path for path in read if "." not in path):
        values.update(_leaves(cfg, key, key, skip))
    for key in CAPTURE_KEYS:
        handed = Path(values[key]).expanduser() if values.get(key) is not None else None
        if handed is not None and handed.exists():
            values[key] = f"content:{capture_digest(handed) if handed.is_dir() else names_and_bytes_digest(handed)}"
    values.update(_handed_in(cfg, kind))
    root = OmegaConf.select(cfg, "paths.root_dir")
    if root is not None:
        values = {key: root_relative(value, root) for key, value in values.items()}
    return dict(sorted(values.items()))


def _handed_in(cfg: DictConfig, kind: str) -> dict[str, str]:
    """The content digests of the inputs handed in by path (``handed_in`` fields) that this run is given
    explicitly (not interpolated)."""
    product = stage_table().product(kind, "run kind")
    found = {}
    for key, declared in _declared(cfg).items():
        if declared.content is None or product not in declared.products:
            continue
        parent, _, leaf = key.rpartition(".")
        holder = OmegaConf.select(cfg, parent)
        # The node is read unresolved: resolving the default would locate the upstream product, which the read
        # fields already name.
        node = holder._get_node(leaf) if isinstance(holder, DictConfig) and leaf in holder.keys() else None
        if node is None or node._is_interpolation() or node._is_none():
            continue
        path = Path(str(node._value())).expanduser()
        found[key] = f"content:{names_and_bytes_digest(path, declared.content)}" if path.exists() else str(node._value())
    return found


def digest(values: dict[str, Any]) -> str:
    payload = json.dumps(values, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:DIGEST_CHARS]


def run_name(cfg: DictConfig, kind: str) -> str:
    """The folder name of a ``kind`` run under ``cfg``: ``seed<k>-<digest>``, from the typed config alone."""
    if kind == "prepare":
        return cache_name(cfg, cfg.data.prepare.split)
    return f"seed{cfg.seed}-{digest(_scoped_values(cfg, kind, _read(cfg, kind)))}"


def differing_keys(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """Keys whose values differ between two ``scoped_values`` records (missing counts as different)."""
    return sorted(k for k in set(recorded) | set(current) if recorded.get(k, "<absent>") != current.get(k, "<absent>"))


def cache_name(cfg: DictConfig, split: str) -> str:
    """The folder name of the paired-clip cache of ``split`` under ``cfg`` (what ``tracegs-prepare
    data.prepare.split=<split>`` writes), also from a run that prepares another split or none."""
    values = _scoped_values(cfg, "prepare", _read(cfg, "prepare", split))
    values["data.prepare.split"] = split
    return f"seed{cfg.seed}-{digest(values)}"


def register_resolvers() -> None:
    """``${tracegs.run:<kind>}``, ``${tracegs.cache:<split>}``, ``${tracegs.seed:<stream>}``,
    ``${tracegs.gpus_per_node:<ranks>,<trainer's GPUs>}``, ``${tracegs.first_set:<a>,<b>,...}`` and the variant's teacher condition
    (``${tracegs.with_variant_teacher:...}``, ``${tracegs.fits_variant_teacher:...}``) and the GSFixer protocol's
    choice (``${tracegs.protocol:<release>,<corrected>}``) for the YAML."""
    OmegaConf.register_new_resolver(
        "tracegs.run", lambda kind, _root_: run_name(_root_, kind), replace=True)
    OmegaConf.register_new_resolver("tracegs.cache", lambda split, _root_: cache_name(_root_, split), replace=True)
    OmegaConf.register_new_resolver("tracegs.product", folder_or_older, replace=True)
    OmegaConf.register_new_resolver(
        "tracegs.seed", lambda stream, _root_: derive_seed(_root_.seed, stream), replace=True)
    OmegaConf.register_new_resolver("tracegs.gpus_per_node", gpus_per_node, replace=True)
    OmegaConf.register_new_resolver("tracegs.first_set", first_set, replace=True)
    OmegaConf.register_new_resolver("tracegs.with_variant_teacher", with_variant_teacher, replace=True)
    OmegaConf.register_new_resolver("tracegs.fits_variant_teacher", fits_variant_teacher, replace=True)
    OmegaConf.register_new_resolver("tracegs.protocol", protocol_value, replace=True)


def protocol_value(release: Any, corrected: Any, _root_: DictConfig) -> Any:
    """``${tracegs.protocol:<release>,<corrected>}``: the value of ``deploy.protocol``'s choice: GSFixer's release
    under gsfixer_release, else the corrected one (``own``, the embedded scale's measured deployment, composed with a
    paper-scale group option, takes the corrections)."""
    return release if str(_root_.deploy.protocol) == "gsfixer_release" else corrected


# The name an older version gave a product folder, before names were derived from the typed config alone: the
# typed overrides after the seed (``seed<k>_<overrides typed>-<digest>``, behind the same prefix as today's).
_OLDER_NAME = re.compile(rf"(?P<head>.*?seed\d+)_.*-(?P<digest>[0-9a-f]{{{DIGEST_CHARS}}})")


def current_name(name: str) -> str | None:
    """Today's name (``<prefix>seed<k>-<digest>``) of the product folder an older version named ``name``; None
    for a name no older version gave."""
    older = _OLDER_NAME.fullmatch(name)
    return None if older is None else f"{older['head']}-{older['digest']}"


def older_folders(folder: Path) -> list[Path]:
    """The folders beside ``folder`` that an older version made for the same product, in name order (one per
    spelling of the command line that made it)."""
    if not folder.parent.is_dir():
        return []
    return sorted(p for p in folder.parent.iterdir() if p.is_dir() and current_name(p.name) == folder.name)


def folder_or_older(path: str) -> str:
    """``path``, a product folder; where it does not exist and an older version's folder of the same product lies
    beside it (one no command renamed yet, e.g. on a read-only copy of an old root), that folder, used where it
    lies. A resolver reads and never writes: renaming older folders is a step of the command
    (tracegs.pipeline.records.migrate_older_folders)."""
    folder = Path(path)
    if folder.exists():
        return path
    older = older_folders(folder)
    return str(older[0]) if older else path


def first_set(*values: Any) -> Any:
    """The first of ``values`` that is not None (None if all are): a setting with a fallback, e.g. a stage's step
    budget, ``trainer.max_steps`` where a debug preset sets it, else the stage's own."""
    return next((value for value in values if value is not None), None)


def gpus_per_node(ranks: int, trainer_gpus: int) -> int:
    """GPUs one cluster job asks for on a node: one per rank where the trainer uses GPUs, none where it does not
    (``trainer.cluster.gpus_per_node`` sizes a training job; a one-process command needs one GPU, not four)."""
    return int(ranks) if int(trainer_gpus) > 0 else 0
