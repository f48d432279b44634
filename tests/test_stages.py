"""The stage table is the product graph's one declaration: a stage added to a copy of it is picked up by every
lookup derived from it (the artifacts a stage loads, the producer of an artifact, a run record's inputs, the
products made from it) and by the modules that read it (the upstream lookup, the run records, the run identity and
the runner), and the real table gives the graph the configs and products were built on."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from support.training_runs import config, write_cache

import tracegs
import tracegs.stages
from tracegs.config.identity import read_fields, run_name
from tracegs.pipeline.records import check_run_record, write_run_record
from tracegs.pipeline.runner import composed
from tracegs.pipeline.upstream import product_folder
from tracegs.products import DEPLOYMENT, Product, declarations, reads
from tracegs.stages import STAGES, Stage, StageName, StageTable
from tracegs.training.run import stage_module, train_stage
from tracegs.training.stage1 import Stage1AlignmentModule

# A pretrained restorer loaded in place of A's training, read by a later stage and by the cache; and a third
# stage made from the students, trained by an existing stage's module.
PRETRAINED = Stage("pretrained", "pretrained_weights", "pretrained_transformer",
                   "tracegs.training.baseline:BaselineRestorerModule", made_into=(Product.stage1,))
STAGE3 = Stage("stage3", "stage3_adapter", "stage3_adapter", "tracegs.training.stage1:Stage1AlignmentModule",
               reads=("pretrained", Product.baseline, Product.stage2), made_into=DEPLOYMENT)


def with_fake_stages() -> StageTable:
    stage2 = dataclasses.replace(STAGES.stage(Product.stage2), made_into=(*DEPLOYMENT, "stage3"))
    stages = tuple(stage2 if stage.product == Product.stage2 else stage for stage in STAGES.stages)
    return dataclasses.replace(STAGES, stages=(PRETRAINED, *stages, STAGE3),
                               also_loading={**STAGES.also_loading, Product.prepare: ("pretrained",)})


@pytest.fixture
def fake_table(monkeypatch):
    """The copy with the fake stages, as the table every lookup reads (tracegs.stages.stage_table)."""
    table = with_fake_stages()
    monkeypatch.setattr(tracegs.stages, "STAGES", table)
    return table


def test_a_stage_added_to_a_copy_of_the_table_is_picked_up_by_every_lookup():
    table = with_fake_stages()
    assert table.names()[0] == "pretrained" and table.names()[-1] == "stage3"
    assert table.stage_inputs("stage3") == ("pretrained_weights", "baseline_weights", "student_adapter")
    assert table.producer("pretrained_weights") == PRETRAINED
    assert table.record_inputs("stage3") == ("pretrained_weights", "baseline_weights", "student_adapter")
    assert table.record_inputs(Product.prepare) == ("pretrained_weights",)
    assert table.made_from(["pretrained"]) == {"pretrained", Product.stage1, Product.stage2, "stage3", *DEPLOYMENT}
    assert table.made_from(["stage3"]) == {"stage3", *DEPLOYMENT}
    assert table.product("stage3", "run kind") == "stage3"
    # The table it was copied from is unchanged.
    assert "stage3" not in STAGES.names() and STAGES.made_from([Product.stage2]) == {Product.stage2, *DEPLOYMENT}


@pytest.fixture
def stage2_command(hydra_context, tmp_path):
    """A Stage-2 command's config, on a config tree with the fake stage's option (conf/stage/stage3.yaml) added."""
    conf = tmp_path / "conf"
    (conf / "stage").mkdir(parents=True)
    (conf / "stage" / "stage3.yaml").write_text(
        "# @package _global_\nstage:\n  max_steps: ${experiment.stage2_steps}\n  batch_size: ${experiment.batch_size}\n"
        "optimizer:\n  lr: ${experiment.stage2_lr}\nrun_dir: ${paths.experiment_dir}/stage3/${tracegs.run:stage3}\n")

    def compose(*overrides: str):
        cfg = composed("train", ["stage=stage2", f"paths.root_dir={tmp_path / 'root'}", *overrides])
        cfg.config_search_path.insert(len(cfg.config_search_path) - 1, f"test=file://{conf}")  # the schema last
        return cfg

    return compose


def test_identity_and_the_upstream_lookup_read_a_stage_added_to_the_table(stage2_command):
    cfg = stage2_command()
    with pytest.raises(ValueError, match="run kind must be one of"):
        run_name(cfg, "stage3")
    table = with_fake_stages()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tracegs.stages, "STAGES", table)
        # Made from the students, it reads every setting Stage 2 reads (the declarations, tracegs.products).
        assert read_fields(cfg, "stage3") == read_fields(cfg, Product.stage2)
        assert "stage3" in declarations(OmegaConf.get_type(cfg))["experiment.stage2_steps"].products
        found = product_folder(cfg, "stage3")
        assert found.parent == Path(cfg.paths.experiment_dir) / "stage3" and found.name.startswith(f"seed{cfg.seed}-")
        # Looked up at its own option's stage sections (the table's stage_sections), not the command's, and
        # named by the experiment's Stage-2 budget, which it reads.
        assert product_folder(stage2_command("optimizer.lr=1e-2", "stage.max_steps=9"), "stage3") == found
        assert product_folder(stage2_command("experiment.stage2_steps=11"), "stage3") != found
    # Declarations are read against the table of the moment: the real one again.
    assert "stage3" not in declarations(OmegaConf.get_type(cfg))["experiment.stage2_steps"].products


def test_the_run_records_hold_the_contents_a_stage_added_to_the_table_loads(stage2_command, fake_table, tmp_path):
    cfg = stage2_command()
    for artifact in ("baseline_weights", "student_adapter"):
        (tmp_path / artifact).mkdir()
        (tmp_path / artifact / "weights.bin").write_bytes(artifact.encode())
        cfg.artifacts[artifact] = str(tmp_path / artifact)
    folder = tmp_path / "stage3_run"
    folder.mkdir()
    write_run_record(cfg, "stage3", folder)
    assert check_run_record(cfg, "stage3", folder)
    # An edit of a product it loads recomputes it.
    (tmp_path / "student_adapter" / "weights.bin").write_bytes(b"edited")
    assert not check_run_record(cfg, "stage3", folder)


def test_the_runner_trains_and_exports_a_stage_added_to_the_table(fake_table, tmp_path):
    assert stage_module("stage3") is Stage1AlignmentModule
    cfg = config(tmp_path, write_cache(tmp_path / "cache"), Product.stage1, 1, "stage3")
    # The config's closed set of stage names is the real table's, fixed with the schema at import; the runner
    # reads the table of the moment.
    cfg.stage.name = "stage3"
    product = train_stage(cfg)
    assert product == tmp_path / "stage3" / STAGE3.folder and (product / "adapter_config.json").is_file()


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

    assert declarations(Section)["x"].products == {Product.baseline, Product.stage1, Product.stage2, *DEPLOYMENT}


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
