"""Run identity: a run's folder is named by the settings that determine its product.

Every product (a paired-clip cache, a trained restorer or adapter, an evaluation) depends on a known
part of the configuration, its *scope*. The folder a run writes to is ``<readable>-<digest>``: the
readable part is the seed and the command-line overrides that fall in the scope, the digest is a hash
of every scoped value after interpolation. So two runs share a folder only when they would produce the
same thing, a changed hyperparameter never resumes or overwrites another run, and a later stage finds
the product it needs by computing the earlier stage's folder with the same rule (``tracegs.pipeline.upstream``).

Keys that change how a run executes but not what it produces (paths, logging, progress bars,
parallelism, sharding, checkpoint cadence) are never part of an identity.

A product is named by the scenes it read: a trained restorer (A, Stage 1, Stage 2) and the training split's
cache by the training scenes, never by the test or validation lists; a cache of another split by that split's
scenes; an evaluation adds its own test scenes to the identity of the restorers it loads. The restorers are
trained on ``training_data`` (a ``data`` option the experiment chooses), so an evaluation of another dataset
(``data=mipnerf360``) finds the students of the experiment's training data (tracegs.pipeline.upstream).

One root ``seed`` drives every stochastic part: each part's own ``seed`` field is derived from it with
:func:`derive_seed` under the part's stream name, so streams differ between parts and between seeds.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from tracegs.content import capture_digest, content_digest, root_relative
from tracegs.restorer.config import (
    ENCODING_SECTIONS,
    NOT_IN_RESTORATIONS,
    RESTORATION_SECTIONS,
    cache_sections,
)

DIGEST_CHARS = 8
READABLE_MAX_CHARS = 80

# Config sections each product depends on (dotted prefixes of the root config).
_DATA = ("data.name", "data.source", "data.synthetic", "data.prepare")
_TRAINING = ("seed", "experiment", "backbone", *_DATA, "data.datamodule", "stage", "optimizer", "trainer")
SCOPES: dict[str, tuple[str, ...]] = {
    # The paired-clip cache: scenes, fits, clips, pseudo-targets and the frozen encoders' outputs (the whole
    # backbone when the pseudo-targets are restorations: ``scope``).
    "prepare": ("seed", *_DATA, *(f"backbone.{section}" for section in ENCODING_SECTIONS)),
    "baseline": _TRAINING,
    # Stage 1 reads lambda_align and the teacher's view set (the R_d it aligns to), on variant A's weights.
    "stage1": (*_TRAINING, "loss.lambda_align", "teacher.views", "artifacts.baseline_weights"),
    "stage2": (*_TRAINING, "loss", "teacher", "policy", "ablation.name", "artifacts.baseline_weights",
               "artifacts.stage1_adapter"),
    # Deployment and evaluation depend on everything that selects the restorers they load: the dataset those
    # were trained on, and the scenes deployed (``data``, the training dataset or another).
    "deploy": (*_TRAINING, "training_data", "loss", "teacher", "policy", "ablation.name", "artifacts", "deploy",
               "evaluation"),
}
SCOPES["evaluate"] = SCOPES["deploy"]
# A capture of the user's own (tracegs-restore): deployment's scope plus which capture and views.
SCOPES["restore"] = (*SCOPES["deploy"], "capture")

# A capture of the user's own is identified by its content, not by where it lies: a folder by its images and
# reconstruction (its photos, when structure-from-motion makes the reconstruction), a video by its bytes.
CAPTURE_KEYS = ("capture.path", "capture.video")
# Inputs a training run may be handed by path instead of locating them (their defaults interpolate the located
# upstream product, whose identity the scope already holds). Handed in, each is known by its content, so runs
# given different weights, adapters or caches are different runs: a cache by its manifest, which records every
# stored tensor's checksum (hashing the tensors themselves would read the whole cache on every run).
HANDED_IN_PARTS: dict[str, tuple[str, ...]] = {"stage.base_weights": (), "stage.init_adapter": (),
                                               "data.datamodule.cache_dir": ("manifest.json",)}
# Execution settings inside scoped sections: they never change a product.
EXECUTION_KEYS = frozenset({
    "data.source.root", "data.synthetic.root",
    "data.prepare.cache_dir", "data.prepare.work_dir", "data.prepare.workers", "data.prepare.shard_index",
    "data.prepare.num_shards", "data.prepare.force", "data.prepare.contact_sheet",
    "data.datamodule.cache_dir", "data.datamodule.num_workers",
    "stage.resume_from", "stage.checkpoint_every_n_steps", "stage.keep_checkpoints", "stage.base_weights",
    "stage.init_adapter", "stage.deployment_eval", "stage.held_out_eval",  # (own random streams: same weights)
    "trainer.log_every_n_steps", "trainer.loggers", "trainer.enable_progress_bar", "trainer.cpu_threads",
    "trainer.slurm_requeue_signal", "trainer.cluster",
    "experiment.description",
    "backbone.transformer.skip_stored_keys",  # stored tensors never loaded: the same model with or without them
    "evaluation.out_dir", "evaluation.shard_index", "evaluation.num_shards", "evaluation.workers",
    "evaluation.force", "evaluation.progress", "evaluation.held_out_cache", "evaluation.variant",
    # Which (scene, views, method) units to compute: each unit is its own file, recorded with its own
    # settings, so selections of units share one evaluation folder and merge into one results.json.
    "evaluation.methods", "evaluation.views", "evaluation.scenes",
    # Which extra files to write beside the numbers (grids, videos, frames, PLYs).
    "evaluation.save_media", "evaluation.save_models", "evaluation.save_frames", "evaluation.grid_views",
    "evaluation.video_frames", "evaluation.video_fps",
    # Where reconstructions are kept and how many threads make them: the reconstruction is keyed by its own inputs.
    "capture.sfm.dir", "capture.sfm.threads",
})
# The keys naming each split's scenes (data.config.Split): a product reads the scenes of the splits it uses only.
SPLIT_SCENES = {
    "train": frozenset({"data.source.train_list", "data.synthetic.train_seeds"}),
    "val": frozenset({"data.synthetic.val_seeds"}),
    "test": frozenset({"data.source.test_list", "data.synthetic.test_seeds"}),
}


def other_splits(*splits: str) -> frozenset[str]:
    """The scene keys of every split but ``splits``."""
    return frozenset().union(*(keys for split, keys in SPLIT_SCENES.items() if split not in splits))


# Training reads the train split's cache whatever split a later prepare builds; the trained restorers never see a
# test or validation scene, deployment and evaluation add the test scenes, a capture of the user's own none.
_TRAINING_KINDS = ("baseline", "stage1", "stage2", "deploy", "evaluate", "restore")
_READ_SPLITS = {"baseline": ("train",), "stage1": ("train",), "stage2": ("train",), "deploy": ("train", "test"),
                "evaluate": ("train", "test"), "restore": ("train",)}
# Training reads latents only: whether a cache keeps frames for inspection, or how held-out clips of short
# captures are filled, leaves the trained restorers as they are.
_NOT_READ_BY_TRAINING = {"data.prepare.split", "data.prepare.store_frames", "data.prepare.held_out_repeat_frames"}
_IGNORED_PER_KIND = {kind: {*_NOT_READ_BY_TRAINING, *other_splits(*_READ_SPLITS[kind])} for kind in _TRAINING_KINDS}
# What only Stage 2 reads: its budget, its rollout, and the deployment grid and sampler it resamples and rolls out
# with. A and Stage 1 never read them, so a Stage-2 sweep reuses one A and one Stage-1 adapter. (Keys of *earlier*
# stages stay in a later stage's scope: its folder is named before the earlier products are located.)
_STAGE2_ONLY = {"experiment.stage2_steps", "experiment.stage2_lr", "experiment.stage2_warmup_steps",
                "experiment.stage2_batch_size",
                "stage.rollout_steps", "stage.memory_mode", "stage.guidance_scale", "loss.trajectory_space",
                "loss.trajectory_target",
                "backbone.schedule.deploy_steps", "backbone.schedule.deploy_time_power", "backbone.sampler"}
_IGNORED_PER_KIND["stage1"] |= _STAGE2_ONLY
# A trains the whole transformer: no adapter, no Stage-1 budget.
_IGNORED_PER_KIND["baseline"] |= {*_STAGE2_ONLY, "experiment.stage1_steps", "experiment.stage1_lr", "backbone.lora"}
# A cache holds what its restorations are made of, not how they are computed (restorer.config).
_IGNORED_PER_KIND["prepare"] = {f"backbone.{key}" for key in NOT_IN_RESTORATIONS}
_IGNORED_PER_KIND = {kind: frozenset(keys) for kind, keys in _IGNORED_PER_KIND.items()}

# Hydra's own overrides and path-like keys never name a run.
_UNNAMED_OVERRIDE_ROOTS = ("hydra", "paths", "run_dir", "task", "seed")
# Group choices already spelled by the folder path (``<experiment>/<stage>/<variant>/``).
_PATH_GROUPS = ("experiment", "stage", "ablation")


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


def scope(cfg: DictConfig, kind: str) -> tuple[str, ...]:
    """The config sections a ``kind`` run's product depends on under ``cfg``: a cache whose pseudo-targets the
    restorer makes depends on the whole backbone."""
    if kind not in SCOPES:
        raise ValueError(f"unknown run kind {kind!r} (one of {sorted(SCOPES)})")
    if kind == "prepare":
        sections = cache_sections(OmegaConf.select(cfg, "data.prepare.pseudo_target"))
        return (*SCOPES[kind], *(f"backbone.{section}" for section in sections if section in RESTORATION_SECTIONS))
    return SCOPES[kind]


def _unread(kind: str, split: str | None = None) -> frozenset[str]:
    """Keys a ``kind`` run never reads (a cache: of ``split``, which reads only that split's scenes)."""
    unread = EXECUTION_KEYS | _IGNORED_PER_KIND.get(kind, frozenset())
    return unread | other_splits(split) if kind == "prepare" else unread


def scoped_values(cfg: DictConfig, kind: str) -> dict[str, Any]:
    """The flattened, resolved values that determine the product of a ``kind`` run.

    A path inside the run's root is kept relative to it, so the same root reached through another spelling, or
    copied or moved, is the same run; a capture handed in is known by its content (tracegs.content)."""
    split = OmegaConf.select(cfg, "data.prepare.split") if kind == "prepare" else None
    return _scoped_values(cfg, kind, _unread(kind, split))


def _scoped_values(cfg: DictConfig, kind: str, skip: frozenset[str]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for key in scope(cfg, kind):
        parent, _, leaf = key.rpartition(".")
        holder = OmegaConf.select(cfg, parent, throw_on_missing=True) if parent else cfg
        values.update(_leaves(holder, leaf, key, skip))
    for key in CAPTURE_KEYS:
        handed = Path(values[key]).expanduser() if values.get(key) is not None else None
        if handed is not None and handed.exists():
            values[key] = f"content:{capture_digest(handed) if handed.is_dir() else content_digest(handed)}"
    values.update(_handed_in(cfg, kind))
    root = OmegaConf.select(cfg, "paths.root_dir")
    if root is not None:
        values = {key: root_relative(value, root) for key, value in values.items()}
    return dict(sorted(values.items()))


def _handed_in(cfg: DictConfig, kind: str) -> dict[str, str]:
    """The content digests of the ``HANDED_IN_PARTS`` inputs this run is given explicitly (not interpolated)."""
    found = {}
    sections = scope(cfg, kind)
    for key, parts in HANDED_IN_PARTS.items():
        parent, _, leaf = key.rpartition(".")
        holder = OmegaConf.select(cfg, parent) if any(key.startswith(f"{s}.") for s in sections) else None
        # The node is read unresolved: resolving the default would locate the upstream product (composing its
        # config), which the scope already names.
        node = holder._get_node(leaf) if isinstance(holder, DictConfig) and leaf in holder.keys() else None
        if node is None or node._is_interpolation() or node._is_none():
            continue
        path = Path(str(node._value())).expanduser()
        found[key] = f"content:{content_digest(path, parts)}" if path.exists() else str(node._value())
    return found


def digest(values: dict[str, Any]) -> str:
    payload = json.dumps(values, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:DIGEST_CHARS]


def override_key(override: str) -> str:
    """``+loss.lambda_ret=0.3`` -> ``loss.lambda_ret``; ``teacher=v12`` -> ``teacher``."""
    return override.split("=", 1)[0].lstrip("+~")


def describes_the_dataset(override: str) -> bool:
    """Whether a command-line override sets the ``data`` group or a key inside it: a setting of the command's own
    dataset, which a step or lookup on another dataset (``data=mipnerf360``) leaves out."""
    return re.split(r"[./]", override_key(override), maxsplit=1)[0] == "data"


def _in_scope(key: str, kind: str, unread: frozenset[str]) -> bool:
    root = re.split(r"[./]", key, maxsplit=1)[0]
    if root in _UNNAMED_OVERRIDE_ROOTS or key in _PATH_GROUPS:
        return False
    if any(key == ignored or key.startswith(ignored + ".") for ignored in unread):
        return False
    # Debug presets set trainer / stage keys (in scope); naming them keeps a debug run recognisable.
    # Otherwise: a group choice (``teacher=v12``) or a key inside a scoped section.
    return key == "debug" or any(key == s or key.startswith(s + ".") or s.startswith(key + ".")
                                 for s in SCOPES[kind])


def readable_name(seed: int, overrides: Sequence[str], kind: str, unread: frozenset[str] | None = None) -> str:
    """``seed<k>`` and the in-scope overrides as ``<last key component>-<value>``, joined by ``_``.

    The name pastes safely into a command line (no ``=``, ``,``, brackets or quotes: Hydra's override syntax),
    names no path (a path value is left to the digest) and cuts no value: overrides that do not fit in
    ``READABLE_MAX_CHARS`` are left out whole and counted (``more<n>``); keys in ``unread`` (default: those a
    ``kind`` run never reads) are not named."""
    unread = _unread(kind) if unread is None else unread
    parts = [f"seed{seed}"]
    left_out = 0
    for override in sorted(set(overrides)):
        key = override_key(override)
        if "=" not in override or not _in_scope(key, kind, unread):
            continue
        value = override.split("=", 1)[1].strip("[]'\"")
        if "/" in value:
            left_out += 1
            continue
        part = re.sub(r"[^A-Za-z0-9.+-]", "_", f"{key.rsplit('.', 1)[-1]}-{value.replace(',', '+')}")
        if len("_".join([*parts, part])) > READABLE_MAX_CHARS:
            left_out += 1
            continue
        parts.append(part)
    return "_".join(parts + ([f"more{left_out}"] if left_out else []))


def run_name(cfg: DictConfig, kind: str, overrides: Sequence[str] = ()) -> str:
    """The folder name of a ``kind`` run under ``cfg``: ``<readable>-<digest>``."""
    if kind == "prepare":
        return cache_name(cfg, cfg.data.prepare.split, overrides)
    return f"{readable_name(cfg.seed, overrides, kind)}-{digest(scoped_values(cfg, kind))}"


def differing_keys(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """Keys whose values differ between two ``scoped_values`` records (missing counts as different)."""
    return sorted(k for k in set(recorded) | set(current) if recorded.get(k, "<absent>") != current.get(k, "<absent>"))


def cache_name(cfg: DictConfig, split: str, overrides: Sequence[str] = ()) -> str:
    """The folder name of the paired-clip cache of ``split`` under ``cfg`` (what ``tracegs-prepare
    data.prepare.split=<split>`` writes), also from a run that prepares another split or none."""
    unread = _unread("prepare", split)
    values = _scoped_values(cfg, "prepare", unread)
    values["data.prepare.split"] = split
    named = [o for o in overrides if override_key(o) != "data.prepare.split"]
    return f"{readable_name(cfg.seed, named, 'prepare', unread)}-{digest(values)}"


def command_line_overrides() -> list[str]:
    """The overrides of the running Hydra job (empty when a config is composed outside a Hydra app)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def register_resolvers() -> None:
    """``${tracegs.run:<kind>}``, ``${tracegs.cache:<split>}``, ``${tracegs.seed:<stream>}`` and
    ``${tracegs.gpus_per_node:<ranks>,<trainer's GPUs>}`` for the YAML."""
    OmegaConf.register_new_resolver(
        "tracegs.run", lambda kind, _root_: run_name(_root_, kind, command_line_overrides()), replace=True)
    OmegaConf.register_new_resolver(
        "tracegs.cache", lambda split, _root_: cache_name(_root_, split, command_line_overrides()), replace=True)
    OmegaConf.register_new_resolver("tracegs.product", product_folder, replace=True)
    OmegaConf.register_new_resolver(
        "tracegs.seed", lambda stream, _root_: derive_seed(_root_.seed, stream), replace=True)
    OmegaConf.register_new_resolver("tracegs.gpus_per_node", gpus_per_node, replace=True)


def product_folder(path: str) -> str:
    """``path`` (a product folder named ``<readable>-<digest>``), or the folder beside it of the same digest that
    already exists: the readable part repeats the command line's in-scope overrides, so two spellings of one
    configuration (a group typed or left to its default, a list typed out) would otherwise make the same product
    twice, in two folders."""
    folder = Path(path)
    if folder.exists() or not folder.parent.is_dir():
        return path
    same = sorted(p for p in folder.parent.glob(f"*-{folder.name.rsplit('-', 1)[-1]}") if p.is_dir())
    return str(same[0]) if same else path


def gpus_per_node(ranks: int, trainer_gpus: int) -> int:
    """GPUs one cluster job asks for on a node: one per rank where the trainer uses GPUs, none where it does not
    (``trainer.cluster.gpus_per_node`` sizes a training job; a one-process command needs one GPU, not four)."""
    return int(ranks) if int(trainer_gpus) > 0 else 0
