"""The pipeline's steps, declared once: (A's pretraining scenes -> A ->) prepare (training and held-out clips)
(-> A) -> Stage 1 -> Stage 2 -> evaluate -> report. Under the paper's data protocol (experiment.baseline_split=
pretrain, the embedded default) A is trained first, on scenes of its own, because the training clips' pseudo-targets
are A applied to R_d; with A trained on the training scenes' ground truth it comes after their preparation. ``tracegs-demo`` runs them in its own process, ``tracegs-replicate`` as child commands (the
restorer's steps once per training seed), the Table 3 sweep as one multirun per step over the variants
(``python -m tracegs.pipeline.steps --sweep [local|slurm] [overrides]``, which ``launch/sweep_ablation.sh`` calls):
one runner (tracegs.pipeline.runner) for all three. Each caller adds only its own settings.

Builders take typed settings (``common``: key -> value for every step) and the user's command-line overrides
(``user``), which each step passes on; a step's own settings win over them.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Mapping, Sequence
from typing import Any

from hydra import compose, initialize_config_dir

from tracegs.config.overrides import describes_the_dataset, override_key
from tracegs.config.schema import register_configs
from tracegs.config.tree import ConfigTree
from tracegs.errors import TraceGSError
from tracegs.location import CONF_DIR
from tracegs.pipeline.runner import NO_SETTINGS, Commands, Step, Sweep, run_steps
from tracegs.pipeline.variants import table3_variants
from tracegs.stages import Product

# The held-out cache: the test scenes prepared like the training clips, read only by evaluation.
HELD_OUT_SPLIT = {"data.prepare.split": "test"}
# The product a step hands on to a later one: the held-out paired-clip cache, which the demo's evaluation reads.
HELD_OUT_CACHE = "held-out cache"
# The cache of variant A's own scenes (experiment.baseline_split=pretrain).
PRETRAIN_SPLIT = {"data.prepare.split": "pretrain"}
# Variant A's run folder, handed on where later steps must load that A whatever their own seed (tracegs-replicate).
BASELINE_RUN = "A's run"

Settings = Mapping[str, Any]


def data_steps(common: Settings = NO_SETTINGS, training: Settings = NO_SETTINGS, held_out: Settings = NO_SETTINGS,
               user: Sequence[str] = ()) -> list[Step]:
    """Prepare the training clips, then the test scenes' held-out clips, which hand their cache's folder on."""
    return [Step.of("prepare", "prepare (training scenes)", common, training).passing(user),
            Step.of("prepare", "prepare (held-out test scenes)", common, HELD_OUT_SPLIT, held_out,
                    hands={HELD_OUT_CACHE: "data.prepare.cache_dir"}).passing(user)]


def baseline_steps(pretrain: bool, common: Settings = NO_SETTINGS, user: Sequence[str] = ()) -> list[Step]:
    """Variant A: with ``pretrain`` (experiment.baseline_split=pretrain) its own scenes prepared first; then A
    trained, handing its run folder on (:data:`BASELINE_RUN`)."""
    prepared = [Step.of("prepare", "prepare (A's pretraining scenes)", common, PRETRAIN_SPLIT).passing(user)]
    return [*(prepared if pretrain else []),
            Step.of("train", "train A", common, {"stage": Product.baseline}, hands={BASELINE_RUN: "run_dir"}).passing(user)]


def in_protocol_order(pretrain: bool, baseline: list[Step], data: list[Step]) -> list[Step]:
    """A's steps and the training data's in the order the data protocol needs: A first where it is pretrained on its
    own scenes (the training clips' pseudo-targets are A on R_d), after the training data where it trains on it."""
    return [*baseline, *data] if pretrain else [*data, *baseline]


def restorer_steps(variant: str | Sweep, common: Settings = NO_SETTINGS, evaluation: Settings = NO_SETTINGS,
                   evaluated: str | Sweep | None = None, stage2: Settings = NO_SETTINGS, user: Sequence[str] = (),
                   evaluation_takes: Mapping[str, str] | None = None) -> list[Step]:
    """Train the Stage-1 adapter and ``variant``'s Stage-2 student (on A, :func:`baseline_steps`), then deploy and
    evaluate them. A sweep names several variants (a :class:`Sweep`), evaluates ``evaluated`` (default:
    ``variant``) and adds ``stage2`` to its Stage-2 step; ``evaluation_takes`` fills evaluation keys from earlier
    steps' products."""
    return [Step.of("train", "train Stage 1", common, {"stage": Product.stage1}).passing(user),
            Step.of("train", "train Stage 2", common, {"stage": Product.stage2, "ablation": variant}, stage2).passing(user),
            Step.of("evaluate", "evaluate", common, {"ablation": evaluated or variant}, evaluation,
                    takes=evaluation_takes or {}).passing(user)]


def out_of_domain_steps(variant: str | Sweep, datasets: Sequence[str], common: Settings = NO_SETTINGS,
                        evaluation: Settings = NO_SETTINGS, user: Sequence[str] = ()) -> list[Step]:
    """Evaluate ``variant``'s restorers, trained on the training data (``training_data``), on each of ``datasets``
    (``data=<name>``, e.g. Mip-NeRF 360): paper Table 2, and Table 3's out-of-domain columns (report.datasets). The
    settings of the command's own dataset are left out: they describe the training data."""
    return [Step.of("evaluate", f"evaluate on {dataset}", _foreign(common),
                    {"ablation": variant, "data": dataset}, evaluation).passing(user, describes_the_dataset)
            for dataset in datasets]


def _foreign(settings: Settings) -> dict[str, Any]:
    """``settings`` less those of the command's own dataset (a DL3DV root or scene list must not become another
    dataset's)."""
    return {key: value for key, value in settings.items() if not describes_the_dataset(key)}


def main_table_steps(datasets: Sequence[str], training_data: str, common: Settings = NO_SETTINGS,
                     swept: Sequence[str] = (), user: Sequence[str] = ()) -> list[Step]:
    """Tables 1/2 (paper Table 1 on DL3DV, Table 2 out of domain: ``report.main_datasets``): on each of
    ``datasets``, plain 3DGS, A and TRACE-GS (F), the restorers trained on ``training_data``, merged by
    ``report.kind=main``: one evaluation of the three, or on a dataset the Table 3 sweep evaluated (``swept``) an
    evaluation of 3DGS alone with A and F taken from the sweep's (``report.main_from_sweep``). On another dataset
    (``data=<name>``) the steps leave out the data settings, which describe the training data."""
    steps = []
    for dataset in datasets:
        own, left_out = (common, None) if dataset == training_data else (
            {**_foreign(common), "data": dataset}, describes_the_dataset)
        if dataset in swept:
            steps += [Step.of("evaluate", f"evaluate 3DGS on {dataset} (Tables 1/2: A and F from the Table 3 sweep)",
                              own, {"evaluation.methods": ["3dgs"]}),
                      Step.of("report", f"Tables 1/2 on {dataset}", own,
                              {"report.kind": "main", "report.main_from_sweep": True})]
        else:
            steps += [Step.of("evaluate", f"evaluate 3DGS, A and F on {dataset} (Tables 1/2)", own),
                      Step.of("report", f"Tables 1/2 on {dataset}", own, {"report.kind": "main"})]
        steps[-2:] = [step.passing(user, left_out or (lambda _: False)) for step in steps[-2:]]
    return steps


# The embedded sweep's cache holds every Table 3 teacher: C and D need 12 and 18 views and B the sparse fits'
# final snapshots (what tracegs.pipeline.variants.variants_teachers derives from Table 3's variants; a test keeps
# the two equal).
SWEEP_TEACHERS = {"data.prepare.dense_views": [12, 18, None], "data.prepare.student_final_fits": True}
# Overrides that leave the embedded synthetic benchmark (its held-out clips are rendered from the known scenes).
NOT_EMBEDDED = ("experiment", "data")
# Fig. 6 on a real dataset: held-out clips through captured images with their photographs as per-frame ground
# truth (tracegs.data.held_out), scored against that truth, so no teacher and no restored pseudo-target; captures
# too short for 49-frame clips at K = 6 and 9 repeat captured frames (data.prepare.held_out_repeat_frames). The
# clips are made at the view counts the tables evaluate (paper: 3, 6 and 9), over which Fig. 6 is averaged.
HELD_OUT_CAPTURED = {**HELD_OUT_SPLIT, "data.prepare.dense_views": [], "data.prepare.pseudo_target": "gt",
                     "data.prepare.student_final_fits": False, "data.prepare.held_out_repeat_frames": True,
                     "data.prepare.student_views": "${evaluation.views}"}
# The per-step report reads the held-out cache its own settings name.
PER_STEP = {"report.kind": "per_step", "evaluation.held_out_cache": "${data.prepare.cache_dir}"}


def sweep_steps(variants: Sequence[str], trained: Sequence[str], user: Sequence[str] = (),
                other_datasets: Sequence[str] = (), pretrain: bool = False) -> list[Step]:
    """Table 3 as multiruns: (embedded scale: prepare) -> A (``pretrain``: on its own scenes, before the training
    data, :func:`in_protocol_order`) -> one shared Stage-1 adapter -> Stage 2 for the
    ``trained`` variants (each cloning the same Stage-1 checkpoint) -> evaluation of every variant by the method
    standing for it, on the training data's test scenes and on each of ``other_datasets`` (Table 3's
    out-of-domain columns) -> Table 3 -> Fig. 6 of the per-step variants on held-out clips (embedded: the
    synthetic test scenes; otherwise: each of ``other_datasets``, paper Fig. 6 on Mip-NeRF 360). ``user``: the
    command line's overrides, passed to every step.

    A SLURM array carries one name: the swept steps name themselves after their first and last variants."""
    embedded = not any(override_key(o).split("/")[0] in NOT_EMBEDDED for o in user)
    common = SWEEP_TEACHERS if embedded else {}
    data = [Step.of("prepare", "prepare (training scenes, every teacher)", common).passing(user)] if embedded else []
    steps = in_protocol_order(pretrain, baseline_steps(pretrain and embedded, common, user), data)
    # Each variant is scored by the method standing for it (the frozen A or its student).
    evaluation = {"evaluation.methods": ["${ablation.method}"], "job_name": f"evaluate-{variants[0]}-{variants[-1]}"}
    steps += restorer_steps(Sweep(tuple(trained)), common, evaluation, evaluated=Sweep(tuple(variants)),
                            stage2={"job_name": f"train-stage2-{trained[0]}-{trained[-1]}"}, user=user)
    steps += out_of_domain_steps(Sweep(tuple(variants)), other_datasets, common, evaluation, user)
    steps.append(Step.of("report", "Table 3", common, {"report.kind": "ablation"}).passing(user))
    if embedded:
        steps += [Step.of("prepare", "prepare (held-out test scenes)", common, HELD_OUT_SPLIT).passing(user),
                  Step.of("report", "Fig. 6", common, HELD_OUT_SPLIT, PER_STEP).passing(user)]
    for dataset in other_datasets:
        held_out = {**_foreign(common), "data": dataset, **HELD_OUT_CAPTURED}
        steps += [Step.of("prepare", f"prepare (held-out {dataset} clips)", held_out),
                  Step.of("report", f"Fig. 6 on {dataset}", held_out, PER_STEP)]
        steps[-2:] = [step.passing(user, describes_the_dataset) for step in steps[-2:]]
    return steps


def run_sweep(launcher: str, user: Sequence[str], dry_run: bool = False) -> int:
    """Run the sweep's steps one after the other, each a multirun through ``launcher`` (tracegs.pipeline.runner);
    stops at the first failed step, exit status 1."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        variants = table3_variants(ConfigTree.at(CONF_DIR))
        table = compose(config_name="report", overrides=list(user))
    other_datasets = [name for name in table.report.datasets if name != table.training_data]
    steps = sweep_steps([v.name for v in variants], [v.name for v in variants if v.train_stage2], user,
                        other_datasets, pretrain=table.experiment.baseline_split == "pretrain")
    try:
        run_steps(steps, Commands(launcher, every_step_multirun=True), "sweep", dry_run)
    except TraceGSError as error:
        print(f"sweep: error: {error}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tracegs.pipeline.steps",
                                     description="Run the Table 3 ablation sweep, one multirun per step.")
    parser.add_argument("--sweep", choices=("local", "slurm"), required=True, help="the hydra/launcher to run on")
    parser.add_argument("--dry-run", action="store_true", help="print the commands without running them")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every step, e.g. experiment=paper")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    return run_sweep(args.sweep, args.overrides, args.dry_run)


if __name__ == "__main__":
    sys.exit(main())
