"""The one runner of step chains (tracegs.pipeline.runner): typed settings reach a command as the values they are,
a product is handed from the step that makes it to the step that takes it, and a failing step stops the chain with
the command that reruns it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra import compose

from tracegs.errors import TraceGSError
from tracegs.pipeline.runner import Commands, Step, Sweep, override, run_steps


@pytest.mark.usefixtures("hydra_context")
def test_typed_settings_compose_to_the_values_they_hold(tmp_path):
    # A folder the user chose may hold override syntax: commas, '=', brackets, quotes, a backslash, a space.
    awkward = tmp_path / "run a,b=[c]'d\\e\\'f\\"
    step = Step.of("evaluate", "evaluate", {"evaluation.out_dir": awkward, "evaluation.views": [3, 6],
                                            "evaluation.save_models": True, "deploy.steps": None,
                                            "evaluation.methods": ["${ablation.method}"], "ablation": "E"})
    cfg = compose(config_name="evaluate", overrides=list(step.overrides))
    assert cfg.evaluation.out_dir == str(awkward)
    assert list(cfg.evaluation.views) == [3, 6] and cfg.evaluation.save_models is True and cfg.deploy.steps is None
    assert [str(m) for m in cfg.evaluation.methods] == ["tracegs"]  # E's own method, by interpolation
    # A path with an interpolation inside stays one quoted value whose interpolation resolves per job.
    per_variant = Step.of("evaluate", "e", {"ablation": "F", "evaluation.out_dir": f"{awkward}/${{ablation.name}}"})
    assert compose(config_name="evaluate", overrides=list(per_variant.overrides)).evaluation.out_dir == f"{awkward}/F"


def test_a_step_wins_over_the_user_and_a_sweep_expands_into_its_jobs():
    step = Step.of("train", "train Stage 2", {"stage": "stage2", "ablation": Sweep(("E", "F"))}).passing(
        ["stage=stage1", "seed=3"])
    assert step.overrides == ("seed=3", "stage=stage2", "ablation=E,F") and step.is_multirun
    assert [(job.label, job.overrides) for job in step.jobs()] == [
        ("train Stage 2 E", ("seed=3", "stage=stage2", "ablation=E")),
        ("train Stage 2 F", ("seed=3", "stage=stage2", "ablation=F"))]
    assert Commands("slurm").command(step)[-5:-3] == ["-m", "hydra/launcher=slurm"]
    assert "-m" not in Commands("slurm").command(step.jobs()[0])
    assert override("data.prepare.dense_views", [12, None]) == "data.prepare.dense_views=[12,null]"


class Recorded:
    """Runs nothing: records the steps it is given and answers for their products from a table (the runner's own
    logic is under test, not the tasks)."""

    def __init__(self, products: dict[tuple[str, str], str]) -> None:
        self.products, self.ran = products, []

    def command(self, step: Step) -> list[str]:
        return [step.app, *step.overrides]

    def run(self, step: Step) -> None:
        self.ran.append(step)

    def product(self, step: Step, key: str) -> str:
        return self.products[step.label, key]


def test_a_product_is_handed_to_the_step_that_takes_it():
    made = Step.of("prepare", "held-out prepare", {"data.prepare.split": "test"},
                   hands={"held-out cache": "data.prepare.cache_dir"})
    taker = Step.of("evaluate", "evaluate", {"evaluation.views": [3]},
                    takes={"evaluation.held_out_cache": "held-out cache"})
    executor = Recorded({("held-out prepare", "data.prepare.cache_dir"): "/root/data/cache/x,y"})
    timings = run_steps([made, taker], executor, "demo")
    assert list(timings) == ["held-out prepare", "evaluate"]
    assert executor.ran[1].overrides == ("evaluation.views=[3]", "evaluation.held_out_cache='/root/data/cache/x,y'")
    with pytest.raises(ValueError, match=r"takes \['held-out cache'\], which no earlier step hands on"):
        run_steps([taker], Recorded({}), "demo")


def test_a_failing_command_stops_the_chain_and_says_how_to_rerun_it(tmp_path):
    failing = Step.of("train", "train A", {"stage": "baseline", "no_such_key": 1, "paths.root_dir": tmp_path})
    # Would write its run folder under the root if the chain went on after the failure.
    later = Step.of("prepare", "prepare", {"paths.root_dir": tmp_path, "data.synthetic.train_seeds": []})
    with pytest.raises(TraceGSError) as error:
        run_steps([failing, later], Commands(), "replicate")
    assert "step 'train A': failed" in str(error.value)
    assert f"rerun it alone: {sys.executable}" in str(error.value) or "tracegs-train" in str(error.value)
    assert "no_such_key=1" in str(error.value) and list(tmp_path.iterdir()) == []


@pytest.mark.usefixtures("hydra_context")
def test_a_child_command_hands_on_the_folder_its_config_names(tmp_path):
    """What a child process wrote is found where its config says, read in the parent without running it."""
    step = Step.of("prepare", "prepare (held-out test scenes)",
                   {"paths.root_dir": tmp_path, "data.prepare.split": "test"})
    cache = Path(Commands().product(step, "data.prepare.cache_dir"))
    assert cache.parent == tmp_path / "data" / "cache" and cache.name.startswith("synthetic-tiny-test-seed0-")
    assert not cache.exists()  # named, not made
