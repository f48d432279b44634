"""The stage table is the product graph's one declaration: a stage added to a copy of it is picked up by every
lookup derived from it (the artifacts a stage loads, the producer of an artifact, a run record's inputs, the
products made from it), and the real table gives the graph the configs and products were built on."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

import tracegs
from tracegs.products import DEPLOYMENT, Product, reads
from tracegs.stages import STAGES, Stage, StageName, StageTable

# A pretrained restorer loaded in place of A's training, read by a later stage and by the cache.
PRETRAINED = Stage("pretrained", "pretrained_weights", "pretrained_transformer", made_into=(Product.stage1,))
STAGE3 = Stage("stage3", "stage3_adapter", "stage3_adapter", reads=("pretrained", Product.stage2),
               made_into=DEPLOYMENT, per_variant=True)


def with_fake_stages() -> StageTable:
    return dataclasses.replace(STAGES, stages=(PRETRAINED, *STAGES.stages, STAGE3),
                               also_loading={**STAGES.also_loading, Product.prepare: ("pretrained",)})


def test_a_stage_added_to_a_copy_of_the_table_is_picked_up_by_every_lookup():
    table = with_fake_stages()
    assert table.names()[0] == "pretrained" and table.names()[-1] == "stage3"
    assert table.stage_inputs("stage3") == ("pretrained_weights", "student_adapter")
    assert table.producer("pretrained_weights") == PRETRAINED
    assert table.record_inputs("stage3") == ("pretrained_weights", "student_adapter")
    assert table.record_inputs(Product.prepare) == ("pretrained_weights",)
    assert table.made_from(["pretrained"]) == {"pretrained", Product.stage1, Product.stage2, *DEPLOYMENT}
    assert table.made_from(["stage3"]) == {"stage3", *DEPLOYMENT}
    # The table it was copied from is unchanged.
    assert "stage3" not in STAGES.names() and STAGES.made_from([Product.stage2]) == {Product.stage2, *DEPLOYMENT}


def test_the_table_gives_the_graph_the_products_were_built_on():
    assert STAGES.names() == (Product.baseline, Product.stage1, Product.stage2)
    assert [s.folder for s in STAGES.stages] == ["baseline_transformer", "stage1_adapter", "student_adapter"]
    assert STAGES.stage_inputs(Product.stage2) == ("baseline_weights", "stage1_adapter")
    assert STAGES.record_inputs(Product.prepare) == ("baseline_weights",)
    assert STAGES.record_inputs(Product.evaluate) == ()
    assert [s.product for s in STAGES.stages if not s.per_variant] == [Product.baseline, Product.stage1]
    assert [member.value for member in StageName] == list(STAGES.names())
    # A field read by A changes every trained stage and the deployments: made-from is transitive.

    @dataclasses.dataclass
    class Section:
        x: int = reads(Product.baseline, default=0)

    assert dataclasses.fields(Section)[0].metadata["tracegs.products"].products == {
        Product.baseline, Product.stage1, Product.stage2, *DEPLOYMENT}


def test_an_unknown_stage_or_artifact_is_named():
    with pytest.raises(KeyError, match="stage.name: 'stage9'"):
        STAGES.stage("stage9")
    with pytest.raises(KeyError, match="artifacts.nothing"):
        STAGES.producer("nothing")


def test_a_trained_stage_is_spelled_in_the_table_alone():
    """The package and its benchmarks name Stage 1 through the table (``Product.stage1``), never by its string:
    renaming or adding a stage then changes one row, not every module that spells it."""
    package = Path(tracegs.__file__).parent
    sources = [*package.rglob("*.py"), *(package.parent / "benchmarks").glob("*.py")]
    spelled = [f"{path.relative_to(package.parent)}:{node.lineno}" for path in sources
               if path != package / "stages.py"
               for node in ast.walk(ast.parse(path.read_text(), filename=str(path)))
               if isinstance(node, ast.Constant) and node.value == Product.stage1.value]
    assert spelled == []
