"""What each entry point does with a composed config: build the components its sections describe, run.

The console scripts in :mod:`tracegs.cli` stay one line each; the demo chains these same functions.
Config sections are turned into the owning package's dataclasses (``OmegaConf.to_object``), so every
component receives typed hyperparameters and never the whole Hydra tree.
"""

from __future__ import annotations

import contextlib
import logging
import resource
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from tracegs.console import show
from tracegs.devices import accelerator

log = logging.getLogger("tracegs")


def section(node: DictConfig) -> Any:
    """The dataclass instance behind a structured config node (interpolations resolved)."""
    return OmegaConf.to_object(node)


# ------------------------------------------------------------------------------------ run identity
RUN_RECORD = "run_identity.json"
# Overrides of Stage 2's own settings and of the ablation axes: they describe the run being started, not
# the earlier runs it builds on (every Table 3 variant clones the one Stage-1 adapter).
_STAGE_OWN = ("stage", "optimizer")
_ABLATION_AXES = ("ablation", "teacher", "policy")


def _carried(override: str, upstream: str, from_training: bool) -> bool:
    from tracegs.config.identity import override_key

    root = override_key(override).split(".")[0].split("/")[0]
    if root == "hydra":
        return False
    if from_training and root in _STAGE_OWN:
        return False
    return not (upstream in ("baseline", "stage1") and root in (*_STAGE_OWN, *_ABLATION_AXES))


def upstream_config(cfg: DictConfig, kind: str, variant: str | None = None) -> DictConfig:
    """The config of the earlier run whose product ``cfg`` needs: the same command line, its own stage.

    ``kind`` is "baseline", "stage1", "stage2" or "evaluate" (the last two for ``variant``, default the
    variant of ``cfg.ablation``). The earlier run's folder follows from this config by the run-identity
    rule (tracegs.config.identity).
    """
    from hydra import compose

    from tracegs.config.identity import command_line_overrides, override_key

    from_training = cfg.task == "train"
    variant = variant or cfg.ablation.name
    extra = {"evaluate": [f"ablation={variant}"],
             "stage2": ["stage=stage2", f"ablation={variant}"]}.get(kind, [f"stage={kind}"])
    replaced = {override_key(o) for o in extra}
    overrides = [o for o in command_line_overrides()
                 if _carried(o, kind, from_training) and override_key(o) not in replaced]
    return compose(config_name="evaluate" if kind == "evaluate" else "train", overrides=[*overrides, *extra])


def locate_artifacts(cfg: DictConfig, needed: Sequence[str]) -> None:
    """Replace each needed "auto" artifact by the product of the run the identity rule finds for ``cfg``.

    The run's own folders are resolved first and kept, so they stay named by the configuration as given.
    """
    from tracegs.config.schema import AUTO
    from tracegs.training.run import PRODUCTS

    for key in ("run_dir", "evaluation.out_dir"):
        OmegaConf.update(cfg, key, str(OmegaConf.select(cfg, key)))
    producers = {"baseline_weights": "baseline", "stage1_adapter": "stage1", "student_adapter": "stage2"}
    for artifact in needed:
        if cfg.artifacts[artifact] != AUTO:
            continue
        producer = producers[artifact]
        cfg.artifacts[artifact] = str(Path(upstream_config(cfg, producer).run_dir) / PRODUCTS[producer])


# The products of earlier runs each kind loads: their content is part of the record (an edit recomputes).
INPUT_ARTIFACTS = {"stage1": ("baseline_weights",), "stage2": ("baseline_weights", "stage1_adapter")}
LOCK_FILE = ".tracegs.lock"


def input_digests(cfg: DictConfig, kind: str) -> dict[str, str]:
    """Content digests of the earlier products a ``kind`` run reads (tracegs.content)."""
    from tracegs.content import content_digest

    paths = {name: OmegaConf.select(cfg, f"artifacts.{name}") for name in INPUT_ARTIFACTS.get(kind, ())}
    return {f"content.{name}": content_digest(path) for name, path in paths.items()
            if path is not None and Path(path).exists()}


def check_run_record(cfg: DictConfig, kind: str, folder: str | Path) -> bool:
    """Whether ``folder`` holds a finished ``kind`` run of exactly ``cfg`` and of the same input contents.

    A folder whose recorded settings differ (an explicit ``run_dir`` or an older version of the code) is
    refused, naming the differing keys, instead of being resumed or overwritten. A folder whose inputs changed
    since its product was made is cleared for recomputation (its checkpoints would resume the stale run).
    """
    import json
    import shutil

    from tracegs.config.identity import differing_keys, scoped_values
    from tracegs.config.validate import ConfigError
    from tracegs.content import root_relative

    record = Path(folder) / RUN_RECORD
    if not record.is_file():
        return False
    recorded = json.loads(record.read_text())
    inputs = input_digests(cfg, kind)
    # Records made before paths were stored relative to the root name them absolutely.
    root = OmegaConf.select(cfg, "paths.root_dir") or "."
    settings = {k: root_relative(v, root) for k, v in recorded.items() if not k.startswith("content.")}
    differing = differing_keys(settings, scoped_values(cfg, kind))
    if differing:
        raise ConfigError(differing[0], f"{folder} holds a run made with other settings "
                          f"({', '.join(differing[:6])} differ): choose another run_dir")
    stale = differing_keys({k: v for k, v in recorded.items() if k.startswith("content.")}, inputs)
    if stale:
        changed = ", ".join(f"artifacts.{key.removeprefix('content.')}" for key in stale)
        log.info("%s: the content of %s changed since this product was made: recomputing it", folder, changed)
        record.unlink()
        shutil.rmtree(Path(folder) / "checkpoints", ignore_errors=True)
        return False
    return True


def reuse_finished(cfg: DictConfig, kind: str, folder: str | Path, product: str | Path) -> bool:
    """Whether ``product`` is the finished product of this very run (same settings and input contents): then
    nothing is done, and the log says so."""
    if check_run_record(cfg, kind, folder) and Path(product).exists():
        log.info("%s: %s already holds this run's product (same settings and inputs): nothing to do", kind, product)
        return True
    return False


@contextlib.contextmanager
def product_lock(folder: str | Path, field: str, shard: tuple[int, int] = (0, 1)) -> Iterator[None]:
    """One job per product folder: a second identical job (another shell, a parallel multirun launcher) waits
    here, then finds the product finished and reuses it. ``shard`` (index, count): the shards of one product
    write their own files and run in parallel, each under its own lock.

    A job that fails leaves no lock file it made, nor the folder if it made it and nothing else is in it (an
    identical job waiting on that lock would fail the same way)."""
    from filelock import FileLock

    from tracegs.errors import require_writable_dir

    folder = require_writable_dir(folder, field)  # a file or a read-only folder: one line naming ``field``
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / (LOCK_FILE if shard[1] == 1 else f"{LOCK_FILE}.shard{shard[0]}of{shard[1]}")
    made_lock = not lock.exists()
    try:
        with FileLock(lock):
            yield
    except BaseException:
        if made_lock:
            lock.unlink(missing_ok=True)
        if created and not any(folder.iterdir()):
            folder.rmdir()
        raise


def write_run_record(cfg: DictConfig, kind: str, folder: str | Path) -> None:
    """Keep beside a finished product the settings that determine it (paths relative to the root), the contents
    of the inputs it was made from, and the whole resolved config."""
    from tracegs.config.identity import scoped_values
    from tracegs.io import atomic_write, write_json_atomic

    folder = Path(folder)
    write_json_atomic({**scoped_values(cfg, kind), **input_digests(cfg, kind)}, folder / RUN_RECORD)
    with atomic_write(folder / "config.yaml") as tmp:
        tmp.write_text(OmegaConf.to_yaml(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True))


# ----------------------------------------------------------------------------------------- prepare
def prepare(cfg: DictConfig) -> Path:
    """Generate the synthetic benchmark if selected, then build the paired-clip cache."""
    from tracegs.data.prepare import require_inputs, run_prepare
    from tracegs.restorer.build import build_backbone

    require_inputs(section(cfg.data.prepare))  # before the backbone loads: bad settings cost nothing
    check_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    shard = (cfg.data.prepare.shard_index, cfg.data.prepare.num_shards)
    with product_lock(cfg.data.prepare.cache_dir, "data.prepare.cache_dir", shard):
        backbone = build_backbone(section(cfg.backbone), device=accelerator())
        synthetic = section(cfg.data.synthetic) if cfg.data.source.preset == "synthetic" else None
        manifest = run_prepare(section(cfg.data.prepare), section(cfg.data.source), backbone, synthetic)
        write_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    log.info("paired-clip cache: %s", manifest)
    return manifest


# ------------------------------------------------------------------------------------------- train
def train(cfg: DictConfig) -> Path | None:
    """Train ``cfg.stage.name`` into ``cfg.run_dir``; variant A trains no Stage 2."""
    from tracegs.training.run import PRODUCTS

    if cfg.stage.name == "stage2" and not cfg.ablation.train_stage2:
        log.info("ablation %s is the frozen baseline restorer: Stage 2 has nothing to train", cfg.ablation.name)
        return None
    if cfg.stage.name == "baseline" and cfg.experiment.baseline_steps == 0:
        # Paper scale: variant A is GSFixer's pretrained restorer, loaded where it is used; the sweep's first
        # command must pass on to Stage 1 rather than stop.
        log.info("experiment %s: variant A is the pretrained restorer %s; nothing to train", cfg.experiment.name,
                 cfg.backbone.transformer.pretrained_path)
        return None
    locate_artifacts(cfg, {"baseline": [], "stage1": ["baseline_weights"],
                           "stage2": ["baseline_weights", "stage1_adapter"]}[cfg.stage.name])
    with product_lock(cfg.run_dir, "run_dir"):
        if reuse_finished(cfg, cfg.stage.name, cfg.run_dir, Path(cfg.run_dir) / PRODUCTS[cfg.stage.name]):
            return Path(cfg.run_dir) / PRODUCTS[cfg.stage.name]
        return train_locked(cfg)


def train_locked(cfg: DictConfig) -> Path:
    """Train (or resume) ``cfg.stage.name`` in its run folder, whose lock this process holds."""
    from tracegs.training.config import TrainConfig
    from tracegs.training.run import train_stage

    train_cfg = TrainConfig(
        stage=section(cfg.stage),
        optimizer=section(cfg.optimizer),
        loss=section(cfg.loss),
        teacher=section(cfg.teacher),
        policy=section(cfg.policy),
        trainer=section(cfg.trainer),
        backbone=section(cfg.backbone),
        data=section(cfg.data.datamodule),
        output_dir=cfg.run_dir,
    )
    product = train_stage(train_cfg)
    write_run_record(cfg, cfg.stage.name, cfg.run_dir)
    log.info("%s product: %s", cfg.stage.name, product)
    return product


# ---------------------------------------------------------------------------------------- restorers
def restorers_for_run(cfg: DictConfig, methods: Sequence[str]) -> dict:
    """Method name -> restorer (None = plain 3DGS), the diffusion methods on one backbone (deploy/assembly.py)."""
    from tracegs.deploy.assembly import RestorerArtifacts, restorer_holdings
    from tracegs.deploy.assembly import build_restorers as assemble
    from tracegs.restorer.memory import holdings_table, loads_pretrained_components

    locate_artifacts(cfg, ["baseline_weights", "student_adapter"])
    backbone = section(cfg.backbone)
    if loads_pretrained_components(backbone):
        show(holdings_table(restorer_holdings(backbone, methods, cfg.deploy.captions.blip2_path)))
    artifacts = RestorerArtifacts(baseline_weights=cfg.artifacts.baseline_weights,
                                  student_adapter=cfg.artifacts.student_adapter, ablation=cfg.ablation.name)
    return assemble(backbone, artifacts, methods, batch=cfg.deploy.clip_batch, steps=cfg.deploy.steps)


# ------------------------------------------------------------------------------------------- scenes
def test_scenes(cfg: DictConfig) -> list[str]:
    """The evaluation scenes: the synthetic benchmark's test seeds (generated if missing) or the dataset's."""
    from tracegs.data.colmap import list_scenes, require_held_out
    from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark

    if cfg.evaluation.scenes is not None:
        if cfg.data.source.preset == "synthetic":
            require_held_out(list(cfg.evaluation.scenes), benchmark_scene_names(section(cfg.data.synthetic), "train"),
                             "evaluation.scenes")
        return list(cfg.evaluation.scenes)
    if cfg.data.source.preset == "synthetic":
        synthetic = section(cfg.data.synthetic)
        generate_benchmark(synthetic, splits=("test",))
        return benchmark_scene_names(synthetic, "test")
    return list_scenes(section(cfg.data.source), "test")


def ground_truth_renderer(cfg: DictConfig):
    """Renders ground truth at any pose where the scene is known (the synthetic benchmark), else None."""
    if cfg.data.source.preset != "synthetic":
        return None
    from tracegs.data.synthetic import render_ground_truth

    return render_ground_truth


# --------------------------------------------------------------------------------- deploy / evaluate
def evaluate(cfg: DictConfig) -> dict:
    """Deploy every method on the test scenes at each view count; write results.json (+ tables, media)."""
    from tracegs.eval.evaluate import evaluate as run_evaluation
    from tracegs.splat.render import require_available

    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    restorers = restorers_for_run(cfg, list(cfg.evaluation.methods))
    check_run_record(cfg, "evaluate", cfg.evaluation.out_dir)
    shard = (cfg.evaluation.shard_index, cfg.evaluation.num_shards)
    with product_lock(cfg.evaluation.out_dir, "evaluation.out_dir", shard):
        results = run_evaluation(
            section(cfg.evaluation),
            section(cfg.data.source),
            section(cfg.deploy),
            section(cfg.data.prepare.fit),
            restorers,
            scenes=test_scenes(cfg),
            gt_renderer=ground_truth_renderer(cfg),
        )
        if cfg.evaluation.held_out_cache is not None:
            held_out_quality(cfg, restorers)
        write_run_record(cfg, "evaluate", cfg.evaluation.out_dir)
    log.info("evaluation written to %s", cfg.evaluation.out_dir)
    return results


def held_out_quality(cfg: DictConfig, restorers: dict) -> Path:
    """Score each diffusion restorer against its input R_s on the held-out clips (eval/clips.py)."""
    from tracegs.eval.clips import clip_restoration_psnr
    from tracegs.eval.report import write_held_out_report

    pipelines = {method: r.pipeline for method, r in restorers.items() if r is not None}
    quality = clip_restoration_psnr(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                    progress=cfg.evaluation.progress)
    table = write_held_out_report(quality, cfg.evaluation.out_dir)
    log.info("held-out clip quality: %s", table)
    return table


def deploy(cfg: DictConfig) -> list[Path]:
    """Restore-refine each test scene at each view count with the selected restorer; save refined PLYs."""
    from tracegs.deploy.scenes import deploy_scenes
    from tracegs.splat.render import require_available

    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    method = "tracegs" if cfg.ablation.train_stage2 else "baseline"
    restorer = restorers_for_run(cfg, [method])[method]
    check_run_record(cfg, "deploy", cfg.run_dir)
    with product_lock(cfg.run_dir, "run_dir", (cfg.evaluation.shard_index, cfg.evaluation.num_shards)):
        written = deploy_scenes(section(cfg.evaluation), section(cfg.data.source), section(cfg.deploy),
                                section(cfg.data.prepare.fit), restorer, test_scenes(cfg), cfg.run_dir)
        write_run_record(cfg, "deploy", cfg.run_dir)
    return written


def restore(cfg: DictConfig) -> Path:
    """Restore and refine a COLMAP capture of your own from K of its views (Algorithm 1, bottom), next to
    plain 3DGS, scored on the views it left out; the evaluation writes the PLYs, the grid and the video."""
    import json
    from dataclasses import replace

    from tracegs.data.splits import SplitError
    from tracegs.errors import ConfigError
    from tracegs.eval.evaluate import evaluate as run_evaluation
    from tracegs.eval.merge import unit_path
    from tracegs.eval.report import results_table_markdown

    if cfg.capture.path is None:
        raise ValueError("capture.path: name the COLMAP scene folder to restore, "
                         "e.g. tracegs-restore capture.path=/data/my_scene")
    capture = Path(cfg.capture.path).expanduser().resolve()
    if not capture.is_dir():
        raise FileNotFoundError(f"capture.path: {capture} is not a directory")
    if not torch.cuda.is_available():
        # One unit of small tensors runs in this process: more intra-op threads only spin (on a shared
        # 2-core machine 2 threads cost 2.5x the CPU time of 1 for the same run).
        torch.set_num_threads(1)
    # The capture is one scene folder: its parent is the dataset root the COLMAP loader reads scenes from.
    source = replace(section(cfg.data.source), root=str(capture.parent), scenes=[capture.name])
    evaluation = section(cfg.evaluation)
    with product_lock(evaluation.out_dir, "evaluation.out_dir"):
        try:
            results = run_evaluation(evaluation, source, section(cfg.deploy), section(cfg.data.prepare.fit),
                                     restorers_for_run(cfg, evaluation.methods), scenes=[capture.name])
        except SplitError as error:  # the user chose the count: capture.views
            raise ConfigError("capture.views", f"{cfg.capture.views}: {capture}: {error}; ask for fewer views or "
                                               "capture more images") from error
    unit = json.loads(unit_path(evaluation.out_dir, capture.name, cfg.capture.views).read_text())
    out = Path(evaluation.out_dir).resolve()  # the unit names its files relative to the evaluation folder
    show(results_table_markdown(results, views=[str(cfg.capture.views)]))
    show(f"\n{capture.name}: fitted from views {unit['captured']}, scored on held-out views {unit['test']}")
    for method, ply in unit["models"].items():
        show(f"refined 3DGS ({method}): {out / ply}")
    show(f"grid: {out / unit['media']['grid']}\nvideo: {out / unit['media']['video']}")
    for method, frames in unit["media"].get("frames", {}).items():
        show(f"trajectory renders ({method}): {out / frames}/")
    return out / unit["models"][evaluation.methods[-1]]


# ------------------------------------------------------------------------------------------- report
def report(cfg: DictConfig) -> Path:
    """Merge evaluation shards (main), prepare shards (prepare) or an ablation sweep (ablation)."""
    from tracegs.data.prepare import merge_manifests
    from tracegs.eval.merge import merge_results
    from tracegs.eval.report import write_ablation_report

    kind = cfg.report.kind
    if kind == "per_step":
        return per_step_report(cfg)
    if kind == "prepare":
        return merge_manifests(cfg.data.prepare.cache_dir)
    if kind == "main":
        out = Path(cfg.evaluation.out_dir)
        merge_results(out, views=list(cfg.evaluation.views), methods=list(cfg.evaluation.methods))
        return out / "results.json"
    if kind == "seeds":
        return seed_report(cfg)
    if kind == "privileged":
        return privileged_report(cfg)
    # report.kind is checked at composition (tracegs.config.schema.ReportKind): the last kind is "ablation".
    inputs = list(cfg.report.inputs) or [upstream_config(cfg, "evaluate", v).evaluation.out_dir
                                         for v in ("A", "B", "C", "D", "E", "F-", "F")]
    table = write_ablation_report([Path(p) for p in inputs], Path(cfg.report.output_dir))
    show(table.read_text())
    intervals = table.with_name("table3_intervals.md")
    if intervals.is_file():
        show(intervals.read_text())
    return table


def privileged_report(cfg: DictConfig) -> Path:
    """The privileged gap (eval/privileged.py): the Stage-1 adapter and the Stage-2 student (this config's
    variant) restore the held-out clips from R_d and from R_s; ``privileged_gap.md`` and ``.json``."""
    from tracegs.deploy.assembly import AdapterFile, shared_restorers
    from tracegs.eval.privileged import privileged_gap, privileged_gap_markdown
    from tracegs.io import atomic_write, write_json_atomic

    if cfg.evaluation.held_out_cache is None:
        raise ValueError("evaluation.held_out_cache: report.kind=privileged needs a prepared held-out cache "
                         "(tracegs-prepare data.prepare.split=test)")
    locate_artifacts(cfg, ["baseline_weights", "stage1_adapter", "student_adapter"])
    if not Path(cfg.artifacts.stage1_adapter).exists():
        raise FileNotFoundError(f"artifacts.stage1_adapter: no Stage-1 adapter at {cfg.artifacts.stage1_adapter} "
                                "(run tracegs-train stage=stage1 with the same settings)")
    pipelines = {name: restorer.pipeline for name, restorer in shared_restorers(
        section(cfg.backbone), cfg.artifacts.baseline_weights,
        {"stage1": AdapterFile(Path(cfg.artifacts.stage1_adapter), "artifacts.stage1_adapter", "stage1", "stage1"),
         "tracegs": AdapterFile(Path(cfg.artifacts.student_adapter), "artifacts.student_adapter", "student")},
        batch=cfg.deploy.clip_batch, steps=cfg.deploy.steps).items()}
    # The student conditions at the view counts evaluated: each is one more restoration per clip and restorer.
    gap = privileged_gap(pipelines, cfg.evaluation.held_out_cache, teacher_views=cfg.teacher.views,
                         student_views=list(cfg.evaluation.views), seed=cfg.deploy.seed,
                         progress=cfg.evaluation.progress)
    out = Path(cfg.report.output_dir)
    write_json_atomic(gap, out / "privileged_gap.json")
    with atomic_write(out / "privileged_gap.md") as tmp:
        tmp.write_text(privileged_gap_markdown(gap))
    show((out / "privileged_gap.md").read_text())
    return out / "privileged_gap.md"


def seed_report(cfg: DictConfig) -> Path:
    """Each figure of several demo runs (one per seed) as mean, sd and range: ``report/seeds.md``."""
    from tracegs.eval.seeds import seed_spread_markdown
    from tracegs.io import atomic_write

    if len(cfg.report.inputs) < 2:
        raise ValueError("report.inputs: report.kind=seeds needs the folders of two or more demo runs")
    table = Path(cfg.report.output_dir) / "seeds.md"
    with atomic_write(table) as tmp:
        tmp.write_text(seed_spread_markdown(list(cfg.report.inputs)))
    show(table.read_text())
    return table


def compose_run(config_name: str, extra: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` with this run's command-line overrides and ``extra`` (which wins), validated."""
    from hydra import compose
    from hydra.core.hydra_config import HydraConfig

    from tracegs.config.validate import validate

    replaced = {override.split("=", 1)[0] for override in extra}
    user = [o for o in HydraConfig.get().overrides.task if o.split("=", 1)[0] not in replaced]
    cfg = compose(config_name=config_name, overrides=[*user, *extra])
    validate(cfg)
    return cfg


def per_step_report(cfg: DictConfig) -> Path:
    """Fig. 6 across variants (default on-policy F vs off-policy E, plus A) on the clips of a prepared cache,
    with each variant's final restoration scored against its input R_s (``held_out_clips.md``).

    Any split's cache works: the test split's held-out clips, or the validation split's
    (``tracegs-prepare data.prepare.split=val``), on which the embedded default's settings are chosen.
    """
    from tracegs.eval.clips import clip_restoration_psnr, held_out_clip_curves
    from tracegs.eval.interval_tables import write_per_step_intervals
    from tracegs.eval.per_step import mean_curves
    from tracegs.eval.report import plot_per_step_quality, write_held_out_report
    from tracegs.io import write_json_atomic

    if cfg.evaluation.held_out_cache is None:
        raise ValueError("evaluation.held_out_cache: report.kind=per_step needs a prepared held-out cache "
                         "(tracegs-prepare data.prepare.split=test)")
    pipelines = {}
    for variant in list(cfg.report.inputs) or ["A", "E", "F"]:
        # Each variant's own config says which restorer stands for it and where its student adapter is.
        variant_cfg = compose_run("report", [f"ablation={variant}"])
        method = variant_cfg.ablation.method
        pipelines[variant] = restorers_for_run(variant_cfg, [method])[method].pipeline
    clip_curves = held_out_clip_curves(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                       progress=cfg.evaluation.progress)
    curves = mean_curves([c for _, c in clip_curves])
    by_scene = {(scene, "all"): mean_curves([c for s, c in clip_curves if s == scene])
                for scene in dict.fromkeys(s for s, _ in clip_curves)}
    out = Path(cfg.report.output_dir)
    write_json_atomic(curves, out / "per_step_variants.json")
    bands = write_per_step_intervals(by_scene, out, "per_step_variants", pairs=[("F", "E"), ("F", "A")])
    figure = plot_per_step_quality(curves, out / "fig6_per_step_variants.png", bands=bands)
    for variant, curve in curves.items():
        show(f"{variant}: " + " ".join(f"{value:.2f}" for value in curve))
    quality = clip_restoration_psnr(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                    progress=cfg.evaluation.progress)
    show(write_held_out_report(quality, out).read_text())
    return figure


# --------------------------------------------------------------------------------------------- demo
def peak_rss_gib() -> float:
    """Peak resident memory of this process and its finished children, in GiB (Linux: ru_maxrss in KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    scale = 1024**3 if sys.platform == "darwin" else 1024**2
    return max(own, children) / scale


# The held-out cache: the benchmark's test scenes prepared like the training clips, read only by evaluation.
HELD_OUT_SPLIT = "data.prepare.split=test"


def demo_steps(views: Sequence[int]) -> list[tuple[str, tuple[str, ...]]]:
    """The demo's commands and their overrides. The test scenes are prepared (held-out clips) and deployed at
    ``views`` input views only (the demo's ``evaluation.views``); the training clips keep every student view
    count. The evaluation's held-out cache is the test prepare's, filled in by ``demo``; it holds no teacher R_d
    (the held-out clips score restorers from R_s only; ``report.kind=privileged`` needs a cache with one)."""
    listed = "[" + ",".join(str(v) for v in views) + "]"
    return [
        ("prepare", ()),
        ("prepare", (HELD_OUT_SPLIT, f"data.prepare.student_views={listed}", "data.prepare.dense_views=[]")),
        ("train", ("stage=baseline",)),
        ("train", ("stage=stage1",)),
        ("train", ("stage=stage2", "ablation=F")),
        ("evaluate", ("ablation=F", HELD_OUT_SPLIT, f"evaluation.views={listed}", "evaluation.save_models=true")),
    ]


def demo(cfg: DictConfig) -> Path:
    """The whole pipeline on the composed experiment: prepare -> A -> Stage 1 -> Stage 2 (F) -> evaluation.

    The evaluation writes straight into the demo's folder (tables, held-out clips, Fig. 6, grids, videos,
    refined PLYs); the demo adds ``run.json`` (commit, seed, machine, timings) and ``tables.md``.
    """
    import lightning

    from tracegs.benchmark import quoted
    from tracegs.io import atomic_write, write_json_atomic
    from tracegs.provenance import describe

    start = time.perf_counter()
    out_dir = Path(cfg.run_dir)
    tasks = {"prepare": prepare, "train": train, "evaluate": evaluate}
    timings: dict[str, float] = {}
    steps = demo_steps(cfg.evaluation.views)
    held_out_cache = None
    for index, (name, extra) in enumerate(steps, 1):
        if name == "evaluate":
            # Quoted: the root the user chose may hold ',' or '=', which unquoted are override syntax.
            extra = (*extra, f"evaluation.held_out_cache={quoted(held_out_cache)}",
                     f"evaluation.out_dir={quoted(out_dir)}")
        step_cfg = compose_run(name, extra)
        if HELD_OUT_SPLIT in extra and name == "prepare":
            held_out_cache = Path(step_cfg.data.prepare.cache_dir)
        lightning.seed_everything(step_cfg.seed, workers=True, verbose=False)
        log.info("[demo %d/%d] %s %s", index, len(steps), name, " ".join(extra))
        step_start = time.perf_counter()
        tasks[name](step_cfg)
        label = " ".join([name, *(e for e in extra if not e.startswith("evaluation."))])
        timings[label] = round(time.perf_counter() - step_start, 1)
    run = {**describe(cfg.seed), "wall_s": round(time.perf_counter() - start, 1),
           "peak_rss_gib": round(peak_rss_gib(), 3), "step_s": timings}
    write_json_atomic(run, out_dir / "run.json")
    with atomic_write(out_dir / "tables.md") as tmp:
        tmp.write_text(demo_tables_markdown(out_dir, run))
    show((out_dir / "tables.md").read_text())
    show(f"tracegs-demo: finished in {run['wall_s']:.0f} s, peak RSS {run['peak_rss_gib']:.2f} GiB")
    show(f"tracegs-demo: tables, grids, videos, refined PLYs and plots in {out_dir.resolve()}")
    return out_dir


def demo_tables_markdown(out_dir: Path, run: dict) -> str:
    """The demo's tables, ready to paste, headed by the run that produced them."""
    import json

    from tracegs.eval.report import results_table_markdown
    from tracegs.eval.seeds import per_step_points

    machine = run["machine"]
    lines = [f"Commit {run['commit']}, seed {run['seed']}, {machine['cpu']} ({machine['cores']} cores, "
             f"torch {machine['torch']}): {run['wall_s'] / 60:.1f} min, peak RSS {run['peak_rss_gib']:.2f} GiB.", "",
             "Deployment on the test scenes:", "",
             results_table_markdown(json.loads((out_dir / "results.json").read_text()))]
    intervals = out_dir / "intervals.md"
    if intervals.is_file():
        scenes = len(json.loads((out_dir / "per_scene.json").read_text()))
        lines += [f"The same with 95% intervals over its {scenes} test scenes (with this few scenes the intervals "
                  "are wide; `make benchmark` runs enough scenes and seeds to resolve smaller gaps):", "",
                  intervals.read_text()]
    held_out = out_dir / "held_out_clips.md"
    if held_out.is_file():
        lines += ["Held-out clips (is the restorer's output closer to ground truth than its input R_s?):", "",
                  held_out.read_text()]
    per_step = out_dir / "per_step.json"
    if per_step.is_file():
        lines += ["Fig. 6, clean-frame prediction along the restorer's own trajectory (PSNR, dB):", "",
                  "| method | first step | minimum | final |", "|---|---|---|---|"]
        for method, curve in json.loads(per_step.read_text()).items():
            points = per_step_points(curve)
            lines.append(f"| {method} | " + " | ".join(f"{points[p]:.2f}" for p in ("first", "min", "final")) + " |")
        lines.append("")
        if (out_dir / "per_step_intervals.md").is_file():
            lines += [(out_dir / "per_step_intervals.md").read_text()]
    return "\n".join(lines)
