"""The paper's scope on SLURM as one chain of jobs, each sized, timed and requeued from the measured rules
(``tracegs.cluster.jobs``), each depending on the one before.

Usage: ``launch/paper_scope.sh --partition P --account A [--dry-run] [--weights-dir weights]
[--measured docs/gpu_check/h200-2026-11-26.json] [--gpu-factor 2.5] [--time-limit-h 48] [--train-scenes 112]
[--dl3dv-test-scenes 28]``

The chain (the scope of the paper's "approximately five days" on four A100s, supplement's computational cost, plus
the evaluations that make Tables 1/2 and Fig. 6):
1. the GPU check with the real weights (``tracegs-weights --check`` first);
2. one prepare shard of the F-only training cache (``variants_teachers`` for F), its wall time the first real
   figure of a unit;
3. the other prepare shards, a SLURM array;
4. Stage 1 and 5. Stage 2 (F) under DDP on 4 GPUs (``launch/slurm_ddp.sbatch``), the requeue signal's lead
   derived from the measured Stage-2 iteration;
6. Tables 1/2 (``tracegs.pipeline.steps.main_table_steps``: each evaluation a sharded array, then its report) and
   Fig. 6 (held-out clips, then the per-step report).

Hours per job come from ``benchmarks/paper_gpu_hours.py``'s work counts at the GPU check's measured seconds per unit
(``--measured``), times ``--gpu-factor`` for the cluster's GPU against the measured one (assumed: an A100 runs bf16
matrix products about 2.5 times slower than an H200; 1 when the check ran on the cluster's own GPU). Shards are
chosen so that none exceeds 80% of the time limit; memory and CPUs per job kind are ``tracegs.cluster.jobs``'s.
``--dry-run`` prints every ``sbatch`` line (``$JOB_<n>`` for the id of job n); otherwise each is submitted with
``--parsable`` and the next depends on its id.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_gpu_hours import (  # noqa: E402
    HOUR,
    PAPER_JOB,
    UnitSeconds,
    compose,
    evaluate_work,
    per_step_work,
    prepare_work,
    test_scenes,
    train_work,
)

from tracegs.cluster.jobs import (  # noqa: E402
    JOB_KINDS,
    SHARD_FILL,
    measured_iteration,
    memory_gb,
    shard_count,
    signal_lead_seconds,
)
from tracegs.cluster.weights import MANIFEST  # noqa: E402
from tracegs.stages import Product  # noqa: E402

GPU_CHECK_HOURS = 1.0  # the check itself: 8 min on an H200 (its JSON) plus the manifest's hashes of ~40 GB
# Assumed: held-out clips through captured cameras need no 3DGS fit or restoration, only renders and encodes.
FIG6_PREPARE_HOURS = 2.0
PREPARE_LEAD_S = 120  # a prepare or evaluate shard saves nothing on the signal: the lead covers scontrol requeue
DDP_GPUS = 4
REPORT_HOURS = 1.0  # assumed: a report merges evaluations (Tables 1/2): minutes
BIN = ".venv/bin/"  # the project's environment, as launch/slurm_ddp.sbatch runs it


@dataclass
class Job:
    """One sbatch line: what runs, on what, for how long, after which job."""

    label: str
    kind: str  # tracegs.cluster.jobs.JOB_KINDS
    command: str  # run through launch/requeue_on_signal.sh, or the DDP sbatch script's arguments
    hours: float  # estimated hours of one task (the longest shard); beyond the limit it requeues and resumes
    gpus: int = 1
    array: int | None = None  # shards of a SLURM array (SLURM_ARRAY_TASK_ID), or one job
    ddp: bool = False
    lead_s: int = PREPARE_LEAD_S

    def runs(self, limit_h: float) -> int:
        """How many runs of the time limit (requeues + 1) the task takes at its estimated hours."""
        return math.ceil(self.hours / (limit_h * SHARD_FILL))

    def sbatch(self, number: int, partition: str, account: str, limit_h: float) -> str:
        # the plan fills SHARD_FILL of the limit; a task longer than that runs the whole limit, then requeues
        limit_min = math.ceil(min(self.hours / SHARD_FILL, limit_h) * 60)
        tasks = self.gpus if self.ddp else 1
        options = [f"--job-name=tracegs-{number}-{self.label}", f"--partition={partition}", f"--account={account}",
                   "--nodes=1", f"--ntasks-per-node={tasks}", f"--gpus-per-node={self.gpus}",
                   f"--cpus-per-task={JOB_KINDS[self.kind].cpus}", f"--mem={memory_gb(self.kind, tasks)}G",
                   f"--time={limit_min // 60:d}:{limit_min % 60:02d}:00", "--requeue"]
        if self.array is not None:
            options.append(f"--array=0-{self.array - 1}")
        if number > 1:
            options.append(f"--dependency=afterok:$JOB_{number - 1}")
        if self.ddp:
            options.append(f"--signal=USR2@{self.lead_s}")
            return "sbatch --parsable " + " ".join(options) + " launch/slurm_ddp.sbatch " + self.command
        options.append(f"--signal=B:USR2@{self.lead_s}")
        return ("sbatch --parsable " + " ".join(options)
                + f" --wrap={shlex.quote('launch/requeue_on_signal.sh ' + self.command)}")


def sharded(units: int, hours_per_unit: float, limit_h: float) -> tuple[int, float]:
    """(shards, hours of the longest shard) of ``units`` at ``hours_per_unit`` under ``limit_h``."""
    shards = shard_count(units, hours_per_unit * HOUR, limit_h * HOUR)
    return shards, math.ceil(units / shards) * hours_per_unit


def cluster_units(record: dict, factor: float) -> UnitSeconds:
    """The GPU check's measured seconds per unit times ``factor`` (the cluster's GPU against the measured one); the
    assumed units are already one A100's, and the training factor is a ratio: both left as they are."""
    unit, sources = UnitSeconds.measured(record)
    scaled = {name: getattr(unit, name) * factor for name, source in sources.items()
              if source.startswith("measured") and name != "training_forward_factor"}
    return replace(unit, **scaled)


def chain(args, unit: UnitSeconds, step_s: float) -> list[Job]:
    """The scope's jobs in order (compose() inside an initialised config directory); ``unit``: the cluster GPU's
    seconds per unit, ``step_s``: the measured Stage-2 iteration's."""
    from tracegs.config.tree import ConfigTree
    from tracegs.location import CONF_DIR
    from tracegs.pipeline.runner import override
    from tracegs.pipeline.steps import main_table_steps, sweep_steps
    from tracegs.pipeline.variants import table3_configs, variants_teachers

    factor, limit = args.gpu_factor, args.time_limit_h
    weights = f"paths.weights_dir={args.weights_dir}"
    # Every command composes the paper's DDP trainer, as the pipeline's steps do: the products' identities (which
    # the evaluations locate the students by) follow it; a one-process command still runs on one GPU.
    common = [*PAPER_JOB, weights]
    teachers = [override(k, v) for k, v in variants_teachers(table3_configs(ConfigTree.at(CONF_DIR), ["F"])).items()]
    prepare_cfg = compose(config_name="prepare", overrides=[*common, *teachers])
    per_scene = prepare_work(prepare_cfg, 1).gpu_hours(unit)
    shards, shard_hours = sharded(args.train_scenes, per_scene, limit)
    shards = max(shards, 2)  # one shard timed alone, the others after it
    prepare = shell(f"{BIN}tracegs-prepare", *common, *teachers, f"data.prepare.num_shards={shards}")
    jobs = [Job("gpu-check", "prepare", f"sh -c {shlex.quote(gpu_check_command(args.weights_dir))}",
                GPU_CHECK_HOURS),
            Job("prepare-shard0", "prepare", f"{prepare} data.prepare.shard_index=0", shard_hours),
            Job("prepare", "prepare", f"{prepare} data.prepare.shard_index=$((SLURM_ARRAY_TASK_ID + 1))",
                shard_hours, array=shards - 1)]
    lead = signal_lead_seconds(step_s * factor)
    for stage in (Product.stage1, Product.stage2):
        cfg = compose(config_name="train", overrides=[*common, f"stage={stage}", "ablation=F"])
        hours = train_work(cfg).gpu_hours(unit) / DDP_GPUS
        command = shell(f"stage={stage}", "ablation=F", weights)  # the sbatch script adds PAPER_JOB
        jobs.append(Job(str(stage), "train", command, hours, gpus=DDP_GPUS, ddp=True, lead_s=lead))
    report = compose(config_name="report", overrides=common)
    for step in main_table_steps(report.report.main_datasets, report.training_data):
        overrides = [*common, *step.overrides]
        cfg = compose(config_name=step.app, overrides=overrides)
        label = step.label.split(" (")[0].replace(" ", "-").replace(",", "").replace("/", "")
        if step.app == "evaluate":
            scenes = test_scenes(cfg, args.dl3dv_test_scenes)
            shards, hours = sharded(scenes, evaluate_work(cfg, 1).gpu_hours(unit), limit)
            command = (shell(f"{BIN}tracegs-evaluate", *overrides, f"evaluation.num_shards={shards}")
                       + " evaluation.shard_index=$SLURM_ARRAY_TASK_ID")
            jobs.append(Job(label, "evaluate", command, hours, array=shards))
        else:
            jobs.append(Job(label, "report", shell(f"{BIN}tracegs-{step.app}", *overrides), REPORT_HOURS))
    # Fig. 6 as the Table 3 sweep declares it: held-out Mip-NeRF 360 clips, then the per-step report.
    held_out, figure = sweep_steps(["A", "F"], ["F"], common, ["mipnerf360"])[-2:]
    cfg = compose(config_name="report", overrides=list(figure.overrides))
    hours = per_step_work(cfg, test_scenes(cfg, args.dl3dv_test_scenes)).gpu_hours(unit)
    jobs += [Job("fig6-held-out", "prepare", shell(f"{BIN}tracegs-prepare", *held_out.overrides), FIG6_PREPARE_HOURS),
             Job("fig6", "report", shell(f"{BIN}tracegs-report", *figure.overrides), hours)]
    return jobs


def shell(*words: str) -> str:
    """A command line the job's shell reads back word for word (Hydra's ${...} and [...] stay literal); the shard
    index, which the shell expands from SLURM's array variable, is appended unquoted by the caller."""
    return shlex.join(words)


def gpu_check_command(weights_dir: str) -> str:
    return (f"{BIN}tracegs-weights --check --weights-dir {shlex.quote(weights_dir)} && "
            f"launch/gpu_check.sh paths.weights_dir={shlex.quote(weights_dir)}")


def main(argv: list[str] | None = None) -> list[str]:
    from hydra import initialize_config_dir

    from tracegs.config.schema import register_configs
    from tracegs.location import CONF_DIR

    parser = argparse.ArgumentParser(prog="launch/paper_scope.sh", description=__doc__.splitlines()[0])
    parser.add_argument("--partition", required=True)
    parser.add_argument("--account", required=True)
    parser.add_argument("--dry-run", action="store_true", help="print the sbatch lines, submit nothing")
    parser.add_argument("--weights-dir", default="weights", help=f"paths.weights_dir (its {MANIFEST} is checked)")
    parser.add_argument("--measured", type=Path, default=Path("docs/gpu_check/h200-2026-11-26.json"))
    parser.add_argument("--gpu-factor", type=float, default=2.5,
                        help="the cluster GPU's seconds over the measured GPU's (assumed 2.5: A100 against H200)")
    parser.add_argument("--time-limit-h", type=float, default=48.0)
    parser.add_argument("--train-scenes", type=int, default=112)
    parser.add_argument("--dl3dv-test-scenes", type=int, default=28)
    args = parser.parse_args(argv)
    try:
        unit = cluster_units(json.loads(args.measured.read_text()), args.gpu_factor)
        step_s, origin = measured_iteration(args.measured)
    except Exception as error:  # noqa: BLE001 (one line for any unreadable record)
        parser.exit(2, f"launch/paper_scope.sh: error: --measured {args.measured}: {error}\n")
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        jobs = chain(args, unit, step_s)
    print(f"# Stage-2 iteration {step_s:.0f} s ({origin}) x {args.gpu_factor} (assumed cluster GPU factor): "
          f"requeue lead {jobs[3].lead_s} s", file=sys.stderr)
    lines = [job.sbatch(number, args.partition, args.account, args.time_limit_h) for number, job in enumerate(jobs, 1)]
    ids: dict[str, str] = {}
    for number, (job, line) in enumerate(zip(jobs, lines), 1):
        if args.dry_run:
            print(f"JOB_{number}=$({line})  # {job.label}: {job.hours:.1f} h per task, "
                  f"{job.runs(args.time_limit_h)} run(s) of the limit")
            continue
        for key, value in ids.items():
            line = line.replace(f"${key}", value)
        ids[f"JOB_{number}"] = subprocess.run(line, shell=True, check=True, capture_output=True,
                                              text=True).stdout.strip().split(";")[0]
        print(f"{ids[f'JOB_{number}']}  {job.label}")
    return lines


if __name__ == "__main__":
    main()
