"""The pipeline's steps, declared once: prepare (training and held-out clips) -> A -> Stage 1 -> Stage 2 ->
evaluate -> report. ``tracegs-demo`` runs them in its own process; ``tracegs-replicate`` runs them as child
commands, the restorer's steps once per training seed; the Table 3 sweep runs each as one multirun over the
variants (``python -m tracegs.pipeline.steps --sweep [local|slurm] [overrides]``, which
``launch/sweep_ablation.sh`` calls). Each caller adds only the overrides of its own setting.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hydra import compose, initialize_config_dir

from tracegs.config.location import CONF_DIR
from tracegs.config.overrides import describes_the_dataset
from tracegs.config.schema import register_configs
from tracegs.pipeline.variants import table3_variants

# The held-out cache: the test scenes prepared like the training clips, read only by evaluation.
HELD_OUT_SPLIT = "data.prepare.split=test"


@dataclass(frozen=True)
class Step:
    """One command: the console script's module under ``tracegs.cli`` (and its ``conf/<app>.yaml``), its
    overrides and what the logs call it."""

    app: str
    overrides: tuple[str, ...]
    label: str

    def command(self) -> list[str]:
        """The step as a child process of this Python."""
        return [sys.executable, "-m", f"tracegs.cli.{self.app}", *self.overrides]

    def multirun(self, launcher: str) -> list[str]:
        """The step as one Hydra multirun through ``hydra/launcher=<launcher>``, by its console script (beside
        this Python) as a user would type it."""
        script = Path(sys.executable).with_name(f"tracegs-{self.app}")
        program = [str(script)] if script.is_file() else [sys.executable, "-m", f"tracegs.cli.{self.app}"]
        return [*program, "-m", f"hydra/launcher={launcher}", *self.overrides]


def data_steps(common: Sequence[str] = (), training: Sequence[str] = (), held_out: Sequence[str] = ()) -> list[Step]:
    """Prepare the training clips, then the test scenes' held-out clips."""
    return [Step("prepare", (*common, *training), "prepare (training scenes)"),
            Step("prepare", (*common, HELD_OUT_SPLIT, *held_out), "prepare (held-out test scenes)")]


def restorer_steps(variant: str, common: Sequence[str] = (), evaluation: Sequence[str] = (),
                   privileged: Sequence[str] | None = None, evaluated: str | None = None,
                   stage2: Sequence[str] = ()) -> list[Step]:
    """Train A, the Stage-1 adapter and ``variant``'s Stage-2 student, then deploy and evaluate them; with
    ``privileged`` (the report's overrides), measure the student's privileged gap as well. A sweep names several
    variants comma-separated, evaluates ``evaluated`` (default: ``variant``) and adds ``stage2`` to its Stage-2
    step."""
    chosen = f"ablation={variant}"
    steps = [Step("train", (*common, "stage=baseline"), "train A"),
             Step("train", (*common, "stage=stage1"), "train Stage 1"),
             Step("train", (*common, "stage=stage2", chosen, *stage2), "train Stage 2"),
             Step("evaluate", (*common, f"ablation={evaluated or variant}", *evaluation), "evaluate")]
    if privileged is not None:
        steps.append(Step("report", (*common, chosen, "report.kind=privileged", *privileged), "privileged gap"))
    return steps


def out_of_domain_steps(variant: str, datasets: Sequence[str], common: Sequence[str] = (),
                        evaluation: Sequence[str] = ()) -> list[Step]:
    """Evaluate ``variant``'s restorers, trained on the training data (``training_data``), on each of ``datasets``
    (``data=<name>``, e.g. Mip-NeRF 360): paper Table 2, and Table 3's out-of-domain columns (report.datasets)."""
    return [Step("evaluate", (*common, f"ablation={variant}", f"data={dataset}", *evaluation), f"evaluate on {dataset}")
            for dataset in datasets]


def main_table_steps(datasets: Sequence[str], training_data: str, common: Sequence[str] = (),
                     swept: Sequence[str] = ()) -> list[Step]:
    """Tables 1/2 (paper Table 1 on DL3DV, Table 2 out of domain: ``report.main_datasets``): on each of
    ``datasets``, plain 3DGS, A and TRACE-GS (F), the restorers trained on ``training_data``, merged by
    ``report.kind=main``: one evaluation of the three, or on a dataset the Table 3 sweep evaluated (``swept``) an
    evaluation of 3DGS alone with A and F taken from the sweep's (``report.main_from_sweep``). On another dataset
    (``data=<name>``) the steps leave out ``common``'s data settings, which describe the training data."""
    steps = []
    for dataset in datasets:
        own = tuple(common) if dataset == training_data else (
            *(o for o in common if not describes_the_dataset(o)), f"data={dataset}")
        if dataset in swept:
            steps += [Step("evaluate", (*own, "evaluation.methods=[3dgs]"),
                           f"evaluate 3DGS on {dataset} (Tables 1/2: A and F from the Table 3 sweep)"),
                      Step("report", (*own, "report.kind=main", "report.main_from_sweep=true"),
                           f"Tables 1/2 on {dataset}")]
        else:
            steps += [Step("evaluate", own, f"evaluate 3DGS, A and F on {dataset} (Tables 1/2)"),
                      Step("report", (*own, "report.kind=main"), f"Tables 1/2 on {dataset}")]
    return steps


# The embedded benchmark's cache holds only the all-view teacher (F); Table 3's C and D need 12 and 18 views and
# B the sparse fits' final snapshots, so the sweep prepares its own cache with them (resumed when there): what
# tracegs.pipeline.variants.teacher_overrides derives from Table 3's variants (a test keeps the two equal).
SWEEP_TEACHERS = ("data.prepare.dense_views=[12,18,null]", "data.prepare.student_final_fits=true")
# Overrides that leave the embedded synthetic benchmark (its held-out clips are rendered from the known scenes).
NOT_EMBEDDED = ("experiment", "data")
# Fig. 6 on a real dataset: held-out clips through captured images with their photographs as per-frame ground
# truth (tracegs.data.held_out), scored against that truth, so no teacher and no restored pseudo-target; captures
# too short for 49-frame clips at K = 6 and 9 repeat captured frames (data.prepare.held_out_repeat_frames). The
# clips are made at the view counts the tables evaluate (paper: 3, 6 and 9), over which Fig. 6 is averaged.
HELD_OUT_CAPTURED = (HELD_OUT_SPLIT, "data.prepare.dense_views=[]", "data.prepare.pseudo_target=gt",
                     "data.prepare.student_final_fits=false", "data.prepare.held_out_repeat_frames=true",
                     "data.prepare.student_views=${evaluation.views}")
# The per-step report reads the held-out cache its own overrides name.
PER_STEP = ("report.kind=per_step", "evaluation.held_out_cache=${data.prepare.cache_dir}")


def sweep_steps(variants: Sequence[str], trained: Sequence[str], overrides: Sequence[str] = (),
                other_datasets: Sequence[str] = ()) -> list[Step]:
    """Table 3 as multiruns: (embedded scale: prepare) -> A -> one shared Stage-1 adapter -> Stage 2 for the
    ``trained`` variants (each cloning the same Stage-1 checkpoint) -> evaluation of every variant by the method
    standing for it, on the training data's test scenes and on each of ``other_datasets`` (Table 3's
    out-of-domain columns) -> Table 3 -> Fig. 6 of the per-step variants on held-out clips (embedded: the
    synthetic test scenes; otherwise: each of ``other_datasets``, paper Fig. 6 on Mip-NeRF 360).

    A SLURM array carries one name: the swept steps name themselves after their first and last variants."""
    embedded = not any(o.split("=", 1)[0].lstrip("+~") in NOT_EMBEDDED for o in overrides)
    common = (*SWEEP_TEACHERS, *overrides) if embedded else tuple(overrides)
    steps = [Step("prepare", common, "prepare (training scenes, every teacher)")] if embedded else []
    # Each variant is scored by the method standing for it (the frozen A or its student).
    evaluation = ("evaluation.methods=[${ablation.method}]", f"job_name=evaluate-{variants[0]}-{variants[-1]}")
    steps += restorer_steps(",".join(trained), common, evaluated=",".join(variants),
                            stage2=(f"job_name=train-stage2-{trained[0]}-{trained[-1]}",), evaluation=evaluation)
    # Steps on another dataset leave out the command line's data settings: they describe the training data (a
    # DL3DV root or scene list must not become Mip-NeRF 360's), as the report's lookup of those steps leaves them out.
    foreign = tuple(o for o in common if not describes_the_dataset(o))
    steps += out_of_domain_steps(",".join(variants), other_datasets, foreign, evaluation)
    steps.append(Step("report", (*common, "report.kind=ablation"), "Table 3"))
    if embedded:
        steps += [Step("prepare", (*common, HELD_OUT_SPLIT), "prepare (held-out test scenes)"),
                  Step("report", (*common, HELD_OUT_SPLIT, *PER_STEP), "Fig. 6")]
    for dataset in other_datasets:
        held_out = (*foreign, f"data={dataset}", *HELD_OUT_CAPTURED)
        steps += [Step("prepare", held_out, f"prepare (held-out {dataset} clips)"),
                  Step("report", (*held_out, *PER_STEP), f"Fig. 6 on {dataset}")]
    return steps


def run_sweep(launcher: str, overrides: Sequence[str], dry_run: bool = False) -> int:
    """Run the sweep's steps one after the other, each a multirun through ``launcher`` (on SLURM the submitit
    launcher waits for a step's jobs, so each step runs on compute nodes and sees the one before finished).
    Stops at the first failed step with its exit status."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        variants = table3_variants()
        table = compose(config_name="report", overrides=list(overrides))
    other_datasets = [name for name in table.report.datasets if name != table.training_data]
    steps = sweep_steps([v.name for v in variants], [v.name for v in variants if v.train_stage2], overrides,
                        other_datasets)
    for index, step in enumerate(steps, 1):
        command = step.multirun(launcher)
        print(f"[sweep {index}/{len(steps)}] {step.label}: {shlex.join(command)}", flush=True)
        if not dry_run:
            status = subprocess.run(command).returncode
            if status != 0:
                return status
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tracegs.pipeline.steps",
                                     description="Run the Table 3 ablation sweep, one multirun per step.")
    parser.add_argument("--sweep", choices=("local", "slurm"), required=True, help="the hydra/launcher to run on")
    parser.add_argument("--dry-run", action="store_true", help="print the commands without running them")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every step, e.g. experiment=paper")
    args = parser.parse_args(argv)
    return run_sweep(args.sweep, args.overrides, args.dry_run)


if __name__ == "__main__":
    sys.exit(main())
