"""The Table 3 variants, read from the config tree: one YAML file per variant in its ``ablation`` group
(conf/ablation/), ordered by the row each declares. Adding a variant is adding its file; the sweep trains and
evaluates it and the Table 3 report lists it. Every function reads the tree it is given (the command's:
``ConfigTree.of(cfg)``, tracegs.config.tree), never a global Hydra context.

``python -m tracegs.pipeline.variants [--trained]`` prints the names comma-separated (the sweep script's list;
``--trained``: only the variants that train a Stage-2 student).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence
from functools import lru_cache
from typing import Any

from omegaconf import DictConfig, OmegaConf

from tracegs.config.schema import AblationConfig, register_configs
from tracegs.config.tree import ConfigTree
from tracegs.data.config import fits_variant_teacher, with_variant_teacher
from tracegs.errors import ConfigError
from tracegs.eval.conclusions import PER_STEP_PAIRS
from tracegs.location import CONF_DIR
from tracegs.stages import stage_table

GROUP = "ablation"
# conf/ablation/default.yaml: which variant a command runs unless given ``ablation=<name>``, not a variant itself.
DEFAULT_CHOICE = "default"


def table3_names(tree: ConfigTree) -> list[str]:
    """The variants' names (the ablation group's files on the tree's search path but the default choice), in no
    particular order."""
    return [option for option in tree.group_options(GROUP) if option != DEFAULT_CHOICE]


@lru_cache(maxsize=32)
def variant_sections(variant: str | None, tree: ConfigTree) -> DictConfig:
    """The sections Table 3 variant ``variant`` sets (None: the default variant's; the stage table's
    ``variant_sections``, tracegs.stages), read from its declaration alone (composed with no command line, once
    per process and config tree)."""
    overrides = [] if variant is None else [f"{GROUP}={variant}"]
    return OmegaConf.masked_copy(tree.compose("train", overrides), list(stage_table().variant_sections))


def table3_configs(tree: ConfigTree, names: Iterable[str] | None = None) -> list[DictConfig]:
    """The training config of every variant of the ablation group (``names``: of those only), in Table 3's row
    order: its ``ablation`` and the groups the variant sets, e.g. ``teacher``.

    A variant's name must be its file's: the run folders (``.../stage2/<name>/``) and the upstream lookup
    (``ablation=<name>``) use it; two variants on one row would leave the table's order undefined."""
    configs = []
    rows: dict[int, str] = {}
    for option in table3_names(tree) if names is None else names:
        cfg = tree.compose("train", [f"{GROUP}={option}"])
        variant = cfg.ablation
        if variant.name != option:
            raise ConfigError(f"{GROUP}.name", f"{GROUP}/{option}.yaml names its variant {variant.name!r}: "
                                               f"name it {option!r}, as its file")
        if variant.row in rows:
            raise ConfigError(f"{GROUP}.row", f"{GROUP}/{option}.yaml and {GROUP}/{rows[variant.row]}.yaml both "
                                              f"take Table 3 row {variant.row}")
        rows[variant.row] = option
        configs.append(cfg)
    return sorted(configs, key=lambda cfg: cfg.ablation.row)


def table3_variants(tree: ConfigTree) -> list[AblationConfig]:
    """Every variant of the ablation group (:func:`table3_configs`), in Table 3's row order."""
    return [OmegaConf.to_object(cfg.ablation) for cfg in table3_configs(tree)]


def teacher_settings(teacher_views: Iterable[int | None], student_views: Sequence[int]) -> dict[str, Any]:
    """The ``data.prepare`` settings that make the teacher conditions of variants distilling from teachers of
    ``teacher_views`` (None: all training views), and no others: tracegs.data.config's rule for the variant a
    command runs for, applied to each. The all-view set is always prepared (its R_d feeds the pseudo-targets and the
    privileged report); a teacher on a student view set (variant B's three views) is that set's final snapshot."""
    dense: list[int | None] = [None]
    final = False
    for views in teacher_views:
        dense = with_variant_teacher(dense, views, list(student_views))
        final = fits_variant_teacher(final, views, list(student_views))
    return {"data.prepare.dense_views": dense, "data.prepare.student_final_fits": final}


def variants_teachers(configs: Iterable[DictConfig]) -> dict[str, Any]:
    """:func:`teacher_settings` of the variants whose training configs are ``configs`` (:func:`table3_configs`)."""
    trained = [cfg for cfg in configs if cfg.ablation.train_stage2]
    student_views = list(trained[0].data.prepare.student_views) if trained else []
    return teacher_settings([cfg.teacher.views for cfg in trained], student_views)


def in_table_order(names: Iterable[str], tree: ConfigTree) -> list[str]:
    """``names`` (variants) sorted by their Table 3 rows."""
    wanted = set(names)
    return [variant.name for variant in table3_variants(tree) if variant.name in wanted]


def per_step_variants(tree: ConfigTree) -> list[str]:
    """The variants Fig. 6 compares (those of the paper's per-step claims), in Table 3's row order."""
    return in_table_order((name for pair in PER_STEP_PAIRS for name in pair), tree)


def main(argv: list[str]) -> None:
    register_configs()
    variants = table3_variants(ConfigTree.at(CONF_DIR))
    print(",".join(v.name for v in variants if v.train_stage2 or "--trained" not in argv))


if __name__ == "__main__":
    main(sys.argv[1:])
