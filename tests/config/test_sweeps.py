"""Sweeps and clusters: `-m` with `--cfg`, a failing multirun job, the SLURM launcher's requests and names."""

from __future__ import annotations

import contextlib
import importlib
import io
import subprocess
import sys
from pathlib import Path
from unittest import mock

import pytest
import yaml

from tracegs.config.tree import ConfigTree
from tracegs.location import CONF_DIR
from tracegs.pipeline.runner import Commands, override
from tracegs.pipeline.steps import SWEEP_TEACHERS, sweep_steps

REPO = Path(__file__).resolve().parents[2]


def command_stdout(command: str, *argv: str) -> str:
    """`tracegs-<command> <argv>` run through its entry point in this process."""
    main = importlib.import_module(f"tracegs.cli.{command}").main
    with mock.patch.object(sys, "argv", [f"tracegs-{command}", *argv]), \
            contextlib.redirect_stdout(io.StringIO()) as out:
        main()
    return out.getvalue()


def train_stdout(*argv: str) -> str:
    return command_stdout("train", *argv)


def test_multirun_cfg_prints_one_config_per_job():
    out = train_stdout("-m", "stage=stage2", "ablation=F,E", "--cfg", "job", "--resolve")
    documents = [yaml.safe_load(d) for d in out.split("---\n") if d.strip()]
    assert [d["ablation"]["name"] for d in documents] == ["F", "E"]
    assert [d["policy"]["on_policy"] for d in documents] == [True, False]  # ablation E is off-policy
    assert "${" not in out


def test_cfg_job_validates_like_the_job_would(capsys):
    """C's teacher sees 12 views, which a cache of the all-view teacher alone does not hold: the job would be
    refused, and so is printing its config."""
    with pytest.raises(SystemExit) as exit_:
        train_stdout("-m", "stage=stage2", "ablation=F,C", "data.prepare.dense_views=[null]", "--cfg", "job")
    captured = capsys.readouterr()
    assert exit_.value.code == 2 and captured.out == ""
    (line,) = [line for line in captured.err.splitlines() if line.strip()]
    assert line.startswith("tracegs-train: error:") and "add it to data.prepare.dense_views" in line


@pytest.mark.parametrize(("trainer", "gpus", "tasks"), [("cpu", 0, 1), ("ddp_sim", 0, 2), ("ddp", 4, 4)])
def test_slurm_launcher_requests_what_the_trainer_uses(trainer, gpus, tasks):
    launcher = yaml.safe_load(train_stdout("hydra/launcher=slurm", f"trainer={trainer}", "stage=stage1",
                                           "--cfg", "hydra", "--resolve"))["launcher"]
    assert launcher["gpus_per_node"] == gpus and launcher["tasks_per_node"] == tasks
    assert launcher["name"] == "tracegs-train-stage1-F"
    if gpus == 0:  # a CPU trainer asks for neither a GPU nor the paper-scale budget
        assert launcher["mem_gb"] < 200 and launcher["timeout_min"] < 2880


@pytest.mark.parametrize("command", ["evaluate", "deploy", "report", "prepare"])
def test_a_one_process_command_asks_slurm_for_one_task_and_one_gpu(command):
    """Only training has ranks: an evaluation on the paper's 4-GPU DDP trainer is one process on one GPU (four
    tasks would run four identical evaluations on the first GPU)."""
    launcher = yaml.safe_load(command_stdout(command, "hydra/launcher=slurm", "experiment=paper", "trainer=ddp",
                                             "--cfg", "hydra", "--resolve"))["launcher"]
    assert (launcher["nodes"], launcher["tasks_per_node"], launcher["gpus_per_node"]) == (1, 1, 1)
    training = yaml.safe_load(train_stdout("hydra/launcher=slurm", "experiment=paper", "trainer=ddp",
                                           "trainer.num_nodes=2", "--cfg", "hydra", "--resolve"))["launcher"]
    assert (training["nodes"], training["tasks_per_node"], training["gpus_per_node"]) == (2, 4, 4)


def test_a_failing_multirun_job_is_reported_and_the_others_run(tmp_path):
    # Variant A trains no Stage 2, so its valid job finishes at once; rollout N=40 fails validation.
    result = subprocess.run(
        [str(Path(sys.executable).with_name("tracegs-train")), "-m", "ablation=A", "stage.rollout_steps=40,5",
         f"paths.root_dir={tmp_path}"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    summary = result.stderr[result.stderr.index("tracegs-train: 1 of 2 multirun jobs succeeded"):].splitlines()
    assert summary[1].startswith("  #0 ablation=A stage.rollout_steps=40 ")
    assert "failed: config field 'stage.rollout_steps'" in summary[1]
    assert summary[2].startswith("  #1 ablation=A stage.rollout_steps=5 ") and summary[2].endswith(": ok")
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("launcher", ["local", "slurm"])
def test_every_step_of_the_sweep_is_a_multirun_through_the_launcher(launcher):
    """On SLURM nothing may run on the login node: each step of the sweep is one multirun through the launcher."""
    variants, trained = ["A", "B", "F"], ["B", "F"]
    embedded = sweep_steps(variants, trained)
    assert [step.app for step in embedded] == ["prepare", "train", "train", "train", "evaluate", "report", "prepare",
                                               "report"]
    teachers = {override(key, value) for key, value in SWEEP_TEACHERS.items()}
    for step in embedded:
        command = Commands(launcher, every_step_multirun=True).command(step)
        assert command[-len(step.overrides) - 2:-len(step.overrides)] == ["-m", f"hydra/launcher={launcher}"]
        assert Path(command[0]).name == f"tracegs-{step.app}" or command[1:3] == ["-m", f"tracegs.cli.{step.app}"]
        assert teachers <= set(step.overrides)  # the embedded sweep's own cache, every teacher
    stage2, evaluate = embedded[3].overrides, embedded[4].overrides
    assert "ablation=B,F" in stage2 and "ablation=A,B,F" in evaluate
    assert "evaluation.methods=[${ablation.method}]" in evaluate
    # another scale: no embedded cache; the other datasets are evaluated with the students of the training data,
    # and Fig. 6 comes from their held-out clips of captured images
    paper = sweep_steps(variants, trained, ["experiment=paper"], ["mipnerf360"])
    assert [step.app for step in paper] == ["train", "train", "train", "evaluate", "evaluate", "report", "prepare",
                                            "report"]
    assert all(not teachers & set(step.overrides) for step in paper)
    out_of_domain, held_out, fig6 = paper[4].overrides, paper[6].overrides, paper[7].overrides
    assert "data=mipnerf360" in out_of_domain and "ablation=A,B,F" in out_of_domain
    assert {"data=mipnerf360", "data.prepare.split=test", "data.prepare.pseudo_target=gt"} <= set(held_out)
    assert set(held_out) < set(fig6) and "report.kind=per_step" in fig6


def test_the_sweep_script_launches_the_declared_steps_over_the_config_variants():
    """launch/sweep_ablation.sh is a launcher of tracegs.pipeline.steps: its dry run lists the declared steps with
    the variants of conf/ablation/."""
    script = (REPO / "launch" / "sweep_ablation.sh").read_text()
    assert [line for line in script.splitlines() if "tracegs-" in line and not line.lstrip().startswith("#")] == []
    run = subprocess.run(["bash", str(REPO / "launch" / "sweep_ablation.sh"), "slurm", "--dry-run", "experiment=paper"],
                         capture_output=True, text=True, timeout=300, check=True)
    lines = run.stdout.splitlines()
    assert len(lines) == 8 and all("-m hydra/launcher=slurm experiment=paper" in line for line in lines)
    assert "ablation=B,C,D,E,F-,F" in lines[2] and "ablation=A,B,C,D,E,F-,F" in lines[3]
    assert "data=mipnerf360" in lines[4] and "Fig. 6 on mipnerf360" in lines[7]  # paper: report.datasets


def test_the_teachers_prepared_are_those_the_variants_distil_from(hydra_context):
    """The embedded sweep's cache holds exactly Table 3's teachers; one variant's run needs only its own (F: the
    all-view set, whose R_d also feeds the pseudo-targets, and no sparse final fits; B: the 3-view final fit)."""
    from tracegs.pipeline.variants import table3_configs, variants_teachers

    assert variants_teachers(table3_configs(ConfigTree.at(CONF_DIR))) == SWEEP_TEACHERS
    assert variants_teachers(table3_configs(ConfigTree.at(CONF_DIR), ["F"])) == {"data.prepare.dense_views": [None],
                                                        "data.prepare.student_final_fits": False}
    assert variants_teachers(table3_configs(ConfigTree.at(CONF_DIR), ["A", "B"])) == {"data.prepare.dense_views": [None],
                                                             "data.prepare.student_final_fits": True}
    assert variants_teachers(table3_configs(ConfigTree.at(CONF_DIR), ["C", "F"]))["data.prepare.dense_views"] == [12, None]
