"""The Table 3 variants, read from the config tree: one YAML file per variant in its ``ablation`` group
(conf/ablation/), ordered by the row each declares. Adding a variant is adding its file; the sweep trains and
evaluates it and the Table 3 report lists it.

``python -m tracegs.pipeline.variants [--trained]`` prints the names comma-separated (the sweep script's list;
``--trained``: only the variants that train a Stage-2 student).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence
from functools import lru_cache
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from tracegs.config.schema import AblationConfig, register_configs
from tracegs.data.config import fits_variant_teacher, with_variant_teacher
from tracegs.errors import ConfigError
from tracegs.eval.conclusions import PER_STEP_PAIRS
from tracegs.location import CONF_DIR

GROUP = "ablation"
# The sections a variant sets: its conf/ablation/<name>.yaml and the teacher, policy and loss options it selects.
VARIANT_SECTIONS = ("ablation", "teacher", "policy", "loss")
# conf/ablation/default.yaml: which variant a command runs unless given ``ablation=<name>``, not a variant itself.
DEFAULT_CHOICE = "default"


def table3_names() -> list[str]:
    """The variants' names (the ablation group's files on the active Hydra search path but the default choice),
    in no particular order."""
    options = GlobalHydra.instance().config_loader().get_group_options(GROUP)
    return [option for option in options if option != DEFAULT_CHOICE]


def _search_path() -> tuple[str, ...]:
    return tuple(str(source.path) for source in GlobalHydra.instance().config_loader().get_sources())


@lru_cache(maxsize=32)
def _variant_sections(variant: str | None, search_path: tuple[str, ...]) -> DictConfig:
    overrides = [] if variant is None else [f"ablation={variant}"]
    cfg = compose(config_name="train", overrides=overrides)
    return OmegaConf.masked_copy(cfg, list(VARIANT_SECTIONS))


def variant_sections(variant: str | None) -> DictConfig:
    """The sections Table 3 variant ``variant`` sets (None: the default variant's), read from its declaration alone
    (composed with no command line, once per process and config search path)."""
    return _variant_sections(variant, _search_path())


def table3_configs(names: Iterable[str] | None = None) -> list[DictConfig]:
    """The training config of every variant of the ablation group (``names``: of those only), in Table 3's row
    order: its ``ablation`` and the groups the variant sets, e.g. ``teacher``.

    A variant's name must be its file's: the run folders (``.../stage2/<name>/``) and the upstream lookup
    (``ablation=<name>``) use it; two variants on one row would leave the table's order undefined."""
    configs = []
    rows: dict[int, str] = {}
    for option in table3_names() if names is None else names:
        cfg = compose(config_name="train", overrides=[f"{GROUP}={option}"])
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


def table3_variants() -> list[AblationConfig]:
    """Every variant of the ablation group (:func:`table3_configs`), in Table 3's row order."""
    return [OmegaConf.to_object(cfg.ablation) for cfg in table3_configs()]


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


def in_table_order(names: Iterable[str]) -> list[str]:
    """``names`` (variants) sorted by their Table 3 rows."""
    wanted = set(names)
    return [variant.name for variant in table3_variants() if variant.name in wanted]


def per_step_variants() -> list[str]:
    """The variants Fig. 6 compares (those of the paper's per-step claims), in Table 3's row order."""
    return in_table_order(name for pair in PER_STEP_PAIRS for name in pair)


def main(argv: list[str]) -> None:
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        variants = table3_variants()
    print(",".join(v.name for v in variants if v.train_stage2 or "--trained" not in argv))


if __name__ == "__main__":
    main(sys.argv[1:])
