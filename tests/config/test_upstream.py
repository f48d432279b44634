"""The upstream lookup projects a run's typed config onto the earlier run whose product it loads: the folder it
finds is the one that earlier run's own command line names, at every scale, debug preset and Table 3 variant,
whatever the later command's own overrides of its stage and variant."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose

from tracegs.pipeline.upstream import as_variant, product_folder, upstream_config

pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py

SCALES = [[], ["experiment=embedded_onestep"], ["experiment=paper"], ["experiment=rehearsal"],
          ["experiment=replicate"]]
# Every scale, and the debug presets, which set the stages' step budgets.
PRESETS = [*SCALES, ["debug=limit"], ["debug=overfit"], ["debug=fdr"], ["experiment=paper", "debug=limit"]]
# Variants whose teacher (B, C), policy (E) or loss (F-) differ from the default variant's; A trains no student.
VARIANTS = ("A", "B", "C", "E", "F-")
# A later command's overrides of its own stage sections and of the variant's axes: its own, never its inputs'.
STAGE2_OWN = ["stage.max_steps=7", "optimizer.lr=2e-4", "optimizer.weight_decay=0.1", "teacher.views=3"]


def folder(config_name: str, overrides: list[str]) -> str:
    cfg = compose(config_name=config_name, overrides=overrides)
    return str(cfg.evaluation.out_dir if config_name == "evaluate" else cfg.run_dir)


@pytest.mark.parametrize("shared", PRESETS, ids=lambda o: "-".join(o) or "embedded")
def test_each_earlier_product_is_found_where_its_own_command_wrote_it(shared):
    earlier = {kind: folder("train", [*shared, f"stage={kind}"]) for kind in ("baseline", "stage1")}
    for variant in VARIANTS if not shared else ("C", "F-"):
        stage2 = compose(config_name="train", overrides=[*shared, "stage=stage2", f"ablation={variant}", *STAGE2_OWN])
        found = {kind: str(upstream_config(stage2, kind).run_dir) for kind in earlier}
        assert found == earlier, variant
        # An evaluation loads its variant's student, trained with the evaluation's own settings of the stage.
        evaluation = compose(config_name="evaluate", overrides=[*shared, f"ablation={variant}", "stage.max_steps=7"])
        assert str(upstream_config(evaluation, "stage2").run_dir) == folder(
            "train", [*shared, "stage=stage2", f"ablation={variant}", "stage.max_steps=7"]), variant
        assert str(upstream_config(evaluation, "baseline").run_dir) == earlier["baseline"], variant


@pytest.mark.parametrize("scale", SCALES[:3], ids=lambda o: "-".join(o) or "embedded")
def test_a_report_finds_every_variants_evaluation_and_student(scale):
    report = compose(config_name="report", overrides=scale)
    for variant in VARIANTS:
        assert product_folder(report, "evaluate", variant) == Path(folder("evaluate", [*scale, f"ablation={variant}"]))
        student = upstream_config(as_variant(report, variant), "stage2")
        assert str(student.run_dir) == folder("train", [*scale, "stage=stage2", f"ablation={variant}"]), variant
        assert student.teacher.views == compose(config_name="train", overrides=[f"ablation={variant}"]).teacher.views


@pytest.mark.parametrize("command", ["prepare", "evaluate", "deploy", "report", "demo"])
def test_every_command_on_the_training_data_finds_the_trained_products(command):
    """A command's own config file (its task, folders, evaluation settings) never changes which restorers it
    loads. (tracegs-restore, whose data section describes a capture, finds them by their run records.)"""
    cfg = compose(config_name=command)
    for kind in ("baseline", "stage1", "stage2"):
        assert product_folder(cfg, kind) == Path(folder("train", [f"stage={kind}"])), kind
