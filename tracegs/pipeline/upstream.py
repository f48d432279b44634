"""Upstream lookup: the config of the earlier run whose product a run needs, and where that product lies.

A later stage never asks where an earlier one wrote: it composes the earlier run's config from its own command
line (``command_line``, which the entry point sets from the overrides it was given) and computes that run's
folder from the typed values with the run-identity rule (tracegs.config.identity). No global Hydra state is
read: a config composed here carries the overrides it was composed from, so it finds its own upstream the same
way.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose
from omegaconf import DictConfig, OmegaConf

from tracegs.config.overrides import describes_the_dataset, override_key, with_overrides
from tracegs.config.schema import AUTO
from tracegs.config.validate import validate
from tracegs.training.run import PRODUCTS


def section(node: DictConfig) -> Any:
    """The dataclass instance behind a structured config node (interpolations resolved)."""
    return OmegaConf.to_object(node)


# Overrides of Stage 2's own settings and of the ablation axes: they describe the run being started, not
# the earlier runs it builds on (every Table 3 variant clones the one Stage-1 adapter).
_STAGE_OWN = ("stage", "optimizer")
_ABLATION_AXES = ("ablation", "teacher", "policy")


# The products a training stage makes: they are looked up on the training data (``training_data``).
TRAINED = ("baseline", "stage1", "stage2")


def _carried(override: str, upstream: str, from_training: bool, other_data: bool) -> bool:
    root = override_key(override).split(".")[0].split("/")[0]
    if root == "hydra" or (other_data and describes_the_dataset(override)):  # settings of the run's own dataset
        return False
    if from_training and root in _STAGE_OWN:
        return False
    return not (upstream in ("baseline", "stage1") and root in (*_STAGE_OWN, *_ABLATION_AXES))


def upstream_config(cfg: DictConfig, kind: str, variant: str | None = None, data: str | None = None) -> DictConfig:
    """The config of the earlier run whose product ``cfg`` needs: the same command line, its own stage.

    ``kind`` is "baseline", "stage1", "stage2" or "evaluate" (the last two for ``variant``, default the
    variant of ``cfg.ablation``), on dataset ``data``: default the training data (``cfg.training_data``) for a
    trained product, this run's for an evaluation. On a dataset other than this run's, the run's ``data``
    overrides are left out (they describe its own dataset). The earlier run's folder follows from this config
    by the run-identity rule (tracegs.config.identity).
    """
    from_training = cfg.task == "train"
    variant = variant or cfg.ablation.name
    data = data or (cfg.training_data if kind in TRAINED else cfg.data.name)
    other_data = data != cfg.data.name
    extra = {"evaluate": [f"ablation={variant}"],
             "stage2": ["stage=stage2", f"ablation={variant}"]}.get(kind, [f"stage={kind}"])
    extra += [f"data={data}"] if other_data else []
    replaced = {override_key(o) for o in extra}
    overrides = [o for o in cfg.command_line
                 if _carried(o, kind, from_training, other_data) and override_key(o) not in replaced]
    return composed("evaluate" if kind == "evaluate" else "train", [*overrides, *extra])


def composed(config_name: str, overrides: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` under ``overrides``, which it keeps as its ``command_line``."""
    cfg = compose(config_name=config_name, overrides=list(overrides))
    cfg.command_line = list(overrides)
    return cfg


def locate_artifacts(cfg: DictConfig, needed: Sequence[str]) -> None:
    """Replace each needed "auto" artifact by the product of the run the identity rule finds for ``cfg``.

    The run's own folders are resolved first and kept, so they stay named by the configuration as given.
    """
    for key in ("run_dir", "evaluation.out_dir"):
        OmegaConf.update(cfg, key, str(OmegaConf.select(cfg, key)))
    producers = {"baseline_weights": "baseline", "stage1_adapter": "stage1", "student_adapter": "stage2"}
    for artifact in needed:
        if cfg.artifacts[artifact] != AUTO:
            continue
        producer = producers[artifact]
        cfg.artifacts[artifact] = str(Path(upstream_config(cfg, producer).run_dir) / PRODUCTS[producer])


def compose_run(cfg: DictConfig, config_name: str, extra: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` with the command-line overrides of ``cfg`` and ``extra`` (which wins),
    validated."""
    cfg = composed(config_name, with_overrides(cfg.command_line, extra))
    validate(cfg)
    return cfg
