"""Table 3's variants are the files of the ablation group: a variant added as one YAML file in a config tree is
composed, gets its own run folders, is listed for the sweep and lands in the Table 3 report."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from tracegs.config.schema import register_configs
from tracegs.config.tree import ConfigTree
from tracegs.config.validate import validate
from tracegs.errors import ConfigError
from tracegs.location import CONF_DIR
from tracegs.pipeline.report import ablation_inputs, ablation_report
from tracegs.pipeline.variants import per_step_variants, table3_variants

# A variant Table 3 does not have: TRACE-GS with twice the retrieval-alignment weight.
NEW_VARIANT = """# @package _global_
# A variant beyond Table 3: TRACE-GS with lambda_ret 0.3
defaults:
  - override /teacher: all
  - override /policy: "on"
  - override /loss: default

ablation:
  name: "G"
  description: "TRACE-GS with lambda_ret 0.3"
  row: 8
  train_stage2: true

loss:
  lambda_ret: 0.3
"""


@pytest.fixture
def conf_with_new_variant(tmp_path) -> Path:
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf, ignore=shutil.ignore_patterns("__pycache__"))
    (conf / "ablation" / "G.yaml").write_text(NEW_VARIANT)
    return conf


@pytest.fixture
def hydra_in(request):
    """Hydra initialised on a config folder; a composed command line stands for the running job's."""
    register_configs()
    contexts = []

    def enter(conf: Path):
        context = initialize_config_dir(config_dir=str(conf), version_base="1.3")
        context.__enter__()
        contexts.append(context)

    yield enter
    for context in contexts:
        context.__exit__(None, None, None)


@pytest.fixture
def schema_registered():
    """The root schema in Hydra's ConfigStore, which every primary config lists first."""
    register_configs()


def test_the_shipped_variants_are_table_3_in_row_order(schema_registered):
    tree = ConfigTree.at(CONF_DIR)
    variants = table3_variants(tree)
    assert [v.row for v in variants] == list(range(1, len(variants) + 1))
    assert [v.name for v in variants] == ["A", "B", "C", "D", "E", "F-", "F"]
    assert [v.name for v in variants if not v.train_stage2] == ["A"]
    assert per_step_variants(tree) == ["A", "E", "F"]  # Fig. 6: A, off-policy E, on-policy F


@pytest.mark.slow  # runs the ablation report on a copied config tree (~18 s)
def test_a_variant_added_as_one_file_is_composed_identified_swept_and_reported(conf_with_new_variant, hydra_in,
                                                                               entry_config, tmp_path):
    hydra_in(conf_with_new_variant)
    # composed
    cfg = compose(config_name="train", overrides=["stage=stage2", "ablation=G"])
    validate(cfg)
    assert cfg.ablation.name == "G" and cfg.loss.lambda_ret == pytest.approx(0.3)
    # identified: its own Stage-2 and evaluation folders, named by it
    names = [v.name for v in table3_variants(ConfigTree.at(str(conf_with_new_variant)))]
    assert names[-1] == "G" and len(names) == 8
    stage2 = {v: str(compose(config_name="train", overrides=["stage=stage2", f"ablation={v}"]).run_dir)
              for v in names}
    assert len(set(stage2.values())) == len(names) and Path(stage2["G"]).parent.name == "G"
    # swept: the sweep script's lists
    env = {**os.environ, "TRACEGS_CONF": str(conf_with_new_variant)}
    listed = [subprocess.run([sys.executable, "-m", "tracegs.pipeline.variants", *flag], env=env, check=True,
                             capture_output=True, text=True).stdout.strip() for flag in ((), ("--trained",))]
    assert listed == [",".join(names), ",".join(names[1:])]
    # reported: Table 3 reads the evaluation folder that `tracegs-evaluate ablation=<name>` writes, the new one's last
    for variant in names:
        evaluation = entry_config("evaluate", [f"ablation={variant}", f"paths.root_dir={tmp_path}"])
        folder = Path(str(evaluation.evaluation.out_dir))
        folder.mkdir(parents=True)
        row = {"psnr": 20.0, "ssim": 0.5, "lpips": 0.2}
        results = {evaluation.ablation.method: {"3": row}, "meta": {"variant": variant}}
        (folder / "results.json").write_text(json.dumps(results))
    report = entry_config("report", ["report.kind=ablation", f"paths.root_dir={tmp_path}",
                                     f"report.output_dir={tmp_path / 'report'}"])
    (inputs,) = ablation_inputs(report).values()
    assert len(set(inputs)) == len(names) and inputs[-1].parent.name == "G"
    table = ablation_report(report).read_text()
    assert [line.split("|")[1].strip() for line in table.splitlines()[2:] if line.startswith("|")][-1] == "G"


@pytest.mark.parametrize(("edit", "field"), [(("name: \"G\"", "name: \"F\""), "ablation.name"),
                                             (("row: 8", "row: 7"), "ablation.row")])
def test_a_variant_that_would_share_a_folder_or_a_row_is_refused(conf_with_new_variant, schema_registered, edit,
                                                                  field):
    new = conf_with_new_variant / "ablation" / "G.yaml"
    new.write_text(new.read_text().replace(*edit))
    with pytest.raises(ConfigError, match=r"ablation/G\.yaml") as error:
        table3_variants(ConfigTree.at(str(conf_with_new_variant)))
    assert error.value.field == field


# Where a variant may be named: its own file, the paper's orderings between variants, and the tests.
NAMING_PLACES = ("conf/ablation/", "tracegs/eval/conclusions.py")


def shipped_variant_names() -> list[str]:
    """The variants as the config tree ships them (its ablation files, the default choice aside)."""
    return [path.stem for path in sorted((Path(CONF_DIR) / "ablation").glob("*.yaml")) if path.stem != "default"]


def variant_naming_pattern(names: list[str]) -> re.Pattern:
    """A variant chosen by name: an ``ablation=X`` / ``ablation: X`` choice, or a field of that name given X."""
    alternatives = "|".join(re.escape(name) for name in sorted(names, key=len, reverse=True))
    return re.compile(rf"\bablation\s*[=:]\s*[\"']?({alternatives})(?![\w-])"
                      rf"|\b(ablation|variant)\w*\s*(:[^=\n]*)?=\s*[\"']({alternatives})[\"']")


def test_the_variant_naming_check_finds_a_chosen_variant():
    pattern = variant_naming_pattern(["A", "F-", "F"])
    chosen = ["  - ablation: F", "tracegs-deploy ablation=A", "ablation=F-,F", '    ablation: str = "F-"',
              'variant = "A"']
    assert all(pattern.search(line) for line in chosen)
    described = ["variant A's weights", "ablation=<variant>", "ablation: default", "the group (conf/ablation/)",
                 "ablation=${ablation.name}", 'ablation: str = "<variant>"']
    assert not any(pattern.search(line) for line in described)


def test_variants_are_chosen_by_name_only_in_their_files_and_the_paper_orderings():
    """Adding, removing or renaming a variant touches conf/ablation/ (and the orderings): no config default, help
    example, launcher or code elsewhere chooses one by name."""
    pattern = variant_naming_pattern(shipped_variant_names())
    repo = Path(CONF_DIR).parent
    files = [*(repo / "tracegs").rglob("*.py"), *Path(CONF_DIR).rglob("*.yaml"), *(repo / "launch").iterdir(),
             repo / "Makefile"]
    offending = []
    for path in sorted(files):
        place = path.relative_to(repo).as_posix()
        if path.is_file() and not place.startswith(NAMING_PLACES):
            lines = enumerate(path.read_text().splitlines(), 1)
            offending += [f"{place}:{number}: {line.strip()}" for number, line in lines if pattern.search(line)]
    assert offending == []
