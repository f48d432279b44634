"""``tracegs-benchmark``: the demo's pipeline replicated over training seeds, on enough scenes to measure.

What depends on the training seed is the restorer: variant A, the Stage-1 adapter and the Stage-2 student
are trained from scratch once per seed in ``benchmark.training_seeds`` (root ``seed`` of those runs). Everything
else is fixed by this run's own root ``seed`` and shared by every replicate: the synthetic scenes, the prepared
training and held-out caches (prepared once), the 3DGS fits and the deployment noise (``data.prepare.seed``,
``data.prepare.fit.seed`` and ``deploy.seed`` are pinned to this seed's values). Plain 3DGS therefore does not
depend on the training seed and is evaluated once, by the first replicate.

Each step is the command a user would type (``tracegs-prepare``, ``-train``, ``-evaluate``, ``-report``), run as
a child process with its overrides on its own command line, so each finds its upstream products by the
run-identity rule exactly as when typed by hand, and every step resumes when the benchmark is rerun.
"""

from __future__ import annotations

import logging
import shlex
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig

from tracegs.config.identity import command_line_overrides, derive_seed, override_key
from tracegs.console import show
from tracegs.errors import TraceGSError
from tracegs.eval.replicates import write_benchmark_report
from tracegs.io import write_json_atomic
from tracegs.pipeline.steps import Step, data_steps, restorer_steps
from tracegs.pipeline.upstream import quoted
from tracegs.provenance import describe, peak_rss_gib

log = logging.getLogger("tracegs")

# Stage timings of `tracegs-demo 'evaluation.views=[3,6,9]'` on an idle 2-core machine (6 training scenes,
# 2 test scenes, four fits per scene), in minutes, and what each scales with: the basis of the wall-time
# estimate printed before the run. Machines of this kind differ by up to 2x.
# Preparing the 12 training scenes took 6.7 min once the sparse fits stopped at their last student snapshot.
PREPARE_PER_TRAIN_SCENE = 6.7 / 12
# Dominated by the scene's 3DGS fits, not by its number of clips: 1.0 min with four full fits, scaled to three
# sparse fits of 340 and one of 600 iterations.
PREPARE_PER_TEST_SCENE = 1.0 * (3 * 340 + 600) / (4 * 600)
# Baseline (A), Stage 1, Stage 2; Stage 2's 20 steps took 25 s in a demo where A's 500 took 107 s (A: 2.0 here).
TRAIN_PER_SEED = 2.0 + 0.6 + 0.5
# Restoring one clip (one condition) with the tiny restorer at 48x72, 9 frames, the deployment schedule:
# 1.5 s measured in a batch of 7 at load 6 on the 2 cores, so about 0.5 s idle (0.0083 min).
RESTORE_PER_CLIP = 0.5 / 60
# The demo's evaluation took 7.2 min: its held-out clips (2 restorers x 16 clips x 6 conditions, ~1.6 min
# by the figure above) and 6 (scene, views) units of 3 methods with grids, videos and Fig. 6 (~5.6 min).
# Plain 3DGS is taken as a third of a unit: it fits the same 600 iterations but restores no clips.
EVAL_PER_UNIT = (7.2 - 2 * 16 * 6 * RESTORE_PER_CLIP) / 6
EVAL_3DGS_SHARE = 1 / 3
STEP_OVERHEAD = 0.15  # starting a child process (torch, Hydra) per step
STUDENT_CONDITIONS = 6  # 3/6/9 views x two snapshots in the held-out cache


def _merge(defaults: Sequence[str], user: Sequence[str]) -> list[str]:
    """``defaults`` with any key the user set on the command line replaced by the user's value."""
    given = {override_key(o) for o in user}
    return [o for o in defaults if override_key(o) not in given] + list(user)


def benchmark_steps(variant: str, root_seed: int, training_seeds: Sequence[int], out_dir: Path,
                    user: Sequence[str] = (), held_out_clips_per_scene: int = 2) -> list[Step]:
    """The pipeline's steps (tracegs.pipeline.steps) for one benchmark run, in order: the data once, the
    restorer's steps per training seed (see the module docstring for what is shared)."""
    if not training_seeds:
        raise ValueError("benchmark.training_seeds: list at least one training seed")
    if len(set(training_seeds)) != len(training_seeds):
        raise ValueError(f"benchmark.training_seeds: {list(training_seeds)} repeats a seed")
    train_cache, test_cache = quoted(out_dir / "cache" / "train"), quoted(out_dir / "cache" / "test")
    shared = ["experiment=benchmark",
              f"data.prepare.seed={derive_seed(root_seed, 'prepare')}",
              f"data.prepare.fit.seed={derive_seed(root_seed, 'fit')}",
              f"deploy.seed={derive_seed(root_seed, 'deploy')}"]
    steps = [Step(step.app, tuple(_merge(step.overrides, user)), step.label) for step in data_steps(
        common=[*shared, f"seed={root_seed}"], training=[f"data.prepare.cache_dir={train_cache}"],
        held_out=[f"data.prepare.clips_per_scene={held_out_clips_per_scene}", f"data.prepare.cache_dir={test_cache}"])]
    for index, seed in enumerate(training_seeds):
        methods = "[3dgs,baseline,tracegs]" if index == 0 else "[baseline,tracegs]"
        replicate = restorer_steps(
            variant, common=[*shared, f"seed={seed}", f"data.datamodule.cache_dir={train_cache}"],
            evaluation=[f"evaluation.methods={methods}", f"evaluation.held_out_cache={test_cache}",
                        f"evaluation.out_dir={quoted(eval_dir(out_dir, seed))}"],
            privileged=[f"evaluation.held_out_cache={test_cache}",
                        f"report.output_dir={quoted(privileged_dir(out_dir, seed))}"])
        steps += [Step(step.app, tuple(_merge(step.overrides, user)),
                       f"seed {seed}: {step.label}" + (f" {methods}" if step.app == "evaluate" else ""))
                  for step in replicate]
    return steps


def eval_dir(out_dir: Path, seed: int) -> Path:
    return out_dir / "eval" / f"seed{seed}"


def privileged_dir(out_dir: Path, seed: int) -> Path:
    return out_dir / "privileged" / f"seed{seed}"


def estimate_minutes(train_scenes: int, test_scenes: int, views: int, seeds: int, steps: int,
                     held_out_clips_per_scene: int) -> float:
    """Wall time from the demo's measured stage timings (module constants), on the same idle machine."""
    units = test_scenes * views
    evaluation = units * EVAL_PER_UNIT + (seeds - 1) * units * EVAL_PER_UNIT * (1 - EVAL_3DGS_SHARE)
    clips = test_scenes * held_out_clips_per_scene
    # Per seed: A and TRACE-GS on every student condition; the privileged gap's two restorers on R_d and the
    # two snapshots of each view count evaluated.
    restorations = seeds * clips * (2 * STUDENT_CONDITIONS + 2 * (1 + 2 * views))
    return (train_scenes * PREPARE_PER_TRAIN_SCENE + test_scenes * PREPARE_PER_TEST_SCENE
            + seeds * TRAIN_PER_SEED + evaluation + restorations * RESTORE_PER_CLIP + steps * STEP_OVERHEAD)


def benchmark(cfg: DictConfig) -> Path:
    """Run every step (each resumes when rerun), then write ``benchmark.md`` into ``cfg.run_dir``."""
    out_dir = Path(cfg.run_dir).resolve()
    seeds = list(cfg.benchmark.training_seeds)
    user = [o for o in command_line_overrides() if override_key(o).split(".")[0] not in ("benchmark", "seed")]
    clips = cfg.benchmark.held_out_clips_per_scene
    steps = benchmark_steps(cfg.ablation.name, cfg.seed, seeds, out_dir, user, clips)
    estimate = estimate_minutes(len(cfg.data.synthetic.train_seeds), len(cfg.data.synthetic.test_seeds),
                                len(cfg.evaluation.views), len(seeds), len(steps), clips)
    show(f"tracegs-benchmark: {len(steps)} steps, about {estimate:.0f} min on two CPU cores; output in {out_dir}")
    start = time.perf_counter()
    timings: dict[str, float] = {}
    for index, step in enumerate(steps, 1):
        log.info("[benchmark %d/%d] %s: %s", index, len(steps), step.label, shlex.join(step.command()[2:]))
        step_start = time.perf_counter()
        if subprocess.run(step.command(), check=False).returncode != 0:
            raise TraceGSError(f"benchmark step '{step.label}'", "failed (its error is printed above)",
                               f"rerun it alone: {shlex.join(step.command())}")
        timings[step.label] = round(time.perf_counter() - step_start, 1)
    run = {**describe(cfg.seed), "training_seeds": seeds, "wall_s": round(time.perf_counter() - start, 1),
           "peak_rss_gib": round(peak_rss_gib(), 3), "step_s": timings, "estimate_min": round(estimate, 1)}
    write_json_atomic(run, out_dir / "run.json")
    machine = run["machine"]
    header = (f"# Embedded benchmark\n\nCommit {run['commit']}, {machine['cpu']} ({machine['cores']} cores, "
              f"torch {machine['torch']}): {run['wall_s'] / 60:.1f} min (estimated {estimate:.0f}), peak RSS "
              f"{run['peak_rss_gib']:.2f} GiB (largest step). Data, 3DGS fits and deployment noise from seed "
              f"{cfg.seed}; the restorer trained from scratch for each training seed.\n")
    report = write_benchmark_report(out_dir, seeds, [eval_dir(out_dir, s) for s in seeds],
                                    [privileged_dir(out_dir, s) for s in seeds], header)
    show(report.read_text())
    return report
