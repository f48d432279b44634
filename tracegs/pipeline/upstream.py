"""Upstream lookup: the config of the earlier run whose product a run needs, and where that product lies.

A later stage never asks where an earlier one wrote: it recomputes the earlier run's folder from its own
command line with the run-identity rule (tracegs.config.identity), so products are found by content.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from tracegs.config.identity import command_line_overrides, describes_the_dataset, override_key
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
    overrides = [o for o in command_line_overrides()
                 if _carried(o, kind, from_training, other_data) and override_key(o) not in replaced]
    return compose(config_name="evaluate" if kind == "evaluate" else "train", overrides=[*overrides, *extra])


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
        folder = same_identity(Path(upstream_config(cfg, producer).run_dir), PRODUCTS[producer])
        cfg.artifacts[artifact] = str(folder / PRODUCTS[producer])


def same_identity(folder: Path, product: str) -> Path:
    """``folder``, or the folder beside it of the same identity (``<readable>-<digest>``, the same digest) that
    holds ``product``. The readable part repeats in-scope overrides of the command line that computes the name,
    and two command lines of one configuration may spell it differently: the training command typed nothing,
    the evaluation of another dataset ``data=mipnerf360``; a group typed or left to the experiment's default."""
    if (folder / product).exists() or not folder.parent.is_dir():
        return folder
    digest = folder.name.rsplit("-", 1)[-1]
    found = sorted(p for p in folder.parent.glob(f"*-{digest}") if (p / product).exists())
    return found[0] if found else folder


def compose_run(config_name: str, extra: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` with this run's command-line overrides and ``extra`` (which wins), validated."""
    replaced = {override.split("=", 1)[0] for override in extra}
    user = [o for o in HydraConfig.get().overrides.task if o.split("=", 1)[0] not in replaced]
    cfg = compose(config_name=config_name, overrides=[*user, *extra])
    validate(cfg)
    return cfg


def quoted(path: Path) -> str:
    """A path as a quoted Hydra override value: run folder names paste safely, but the root the user chose may
    hold commas, brackets or '=', which would otherwise be parsed as override syntax."""
    return "'" + str(path).replace("\\", "\\\\").replace("'", "\\'") + "'"
