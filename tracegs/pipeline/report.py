"""``tracegs-report``: one function per report kind (tracegs.config.schema.ReportKind)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from tracegs.config.tree import ConfigTree
from tracegs.console import show
from tracegs.deploy.assembly import AdapterFile, shared_restorers
from tracegs.eval.clips import (
    clip_restoration_psnr,
    held_out_clip_curves,
    per_step_breakdown,
    per_step_breakdown_markdown,
    unit_curves,
    view_averaged_curves,
)
from tracegs.eval.conclusions import PER_STEP_PAIRS
from tracegs.eval.html_report import write_report_page
from tracegs.eval.interval_tables import write_per_step_intervals
from tracegs.eval.labels import STAGE1
from tracegs.eval.merge import merge_results
from tracegs.eval.privileged import privileged_gap, privileged_gap_markdown
from tracegs.eval.seeds import seed_spread_markdown
from tracegs.eval.tables_and_figures import (
    plot_per_step_quality,
    write_ablation_report,
    write_held_out_report,
)
from tracegs.io import atomic_write, write_json_atomic
from tracegs.pipeline.diagnostics import diagnostics_report
from tracegs.pipeline.restorers import restorers_for_run
from tracegs.pipeline.upstream import as_variant, locate_artifacts, product_folder, section
from tracegs.pipeline.variants import per_step_variants, table3_variants
from tracegs.products import Product
from tracegs.stages import stage_table


def report(cfg: DictConfig) -> Path:
    """Merge evaluation shards (main), an ablation sweep (ablation), or another kind."""
    kind = cfg.report.kind
    if kind == "main":
        out = Path(cfg.evaluation.out_dir)
        sources = swept_method_evaluations(cfg) if cfg.report.main_from_sweep else None
        merge_results(out, views=list(cfg.evaluation.views), methods=list(cfg.evaluation.methods), sources=sources)
        write_report_page(out)
        return out / "results.json"
    # report.kind is checked at composition (tracegs.config.schema.ReportKind).
    return {"per_step": per_step_report, "seeds": seed_report, "privileged": privileged_report,
            "ablation": ablation_report, "diagnostics": diagnostics_report}[kind](cfg)


def variant_evaluation(cfg: DictConfig, variant: str, dataset: str, asked_by: str, product: str = "results.json"
                       ) -> Path:
    """The folder of the evaluation of ``variant`` on ``dataset`` that this command line's settings give (what the
    ablation sweep's evaluate step made), refused in one line naming the field ``asked_by`` when it lacks
    ``product``."""
    folder = product_folder(cfg, "evaluate", variant, data=dataset)
    if not (folder / product).exists():
        raise FileNotFoundError(f"{asked_by}: no evaluation of variant {variant} on {dataset} ({folder / product}); run "
                                f"tracegs-evaluate ablation={variant} data={dataset} with this command's settings")
    return folder


def swept_method_evaluations(cfg: DictConfig) -> dict[str, Path]:
    """Tables 1/2 from the ablation sweep (``report.main_from_sweep``): each restorer method of
    ``evaluation.methods`` from the sweep's evaluation, on this dataset, of the variant standing for it: this
    command's variant (default F) for its own method, else the one variant evaluated by that method (A for
    ``baseline``). 3DGS, which no variant stands for, stays this command's own evaluation."""
    standing = {v.method: v.name for v in reversed(table3_variants(ConfigTree.of(cfg)))} | {cfg.ablation.method: cfg.ablation.name}
    unknown = [m for m in cfg.evaluation.methods if m != "3dgs" and m not in standing]
    if unknown:
        raise ValueError(f"report.main_from_sweep: no Table 3 variant is evaluated by {unknown}")
    return {m: variant_evaluation(cfg, standing[m], cfg.data.name, "report.main_from_sweep", "units")
            for m in cfg.evaluation.methods if m != "3dgs"}


def ablation_inputs(cfg: DictConfig) -> dict[str, list[Path]]:
    """Per dataset, the evaluation folder of every variant: ``report.inputs`` (this command's dataset), else for
    each of ``report.datasets`` the evaluation of every variant (conf/ablation/) that this command line's settings
    give on it, in Table 3's row order (the restorers trained on the training data, evaluated there)."""
    if cfg.report.inputs:
        return {cfg.data.name: [Path(p) for p in cfg.report.inputs]}
    return {dataset: [variant_evaluation(cfg, variant.name, dataset, "report.datasets") for variant in table3_variants(ConfigTree.of(cfg))]
            for dataset in cfg.report.datasets}


def ablation_report(cfg: DictConfig) -> Path:
    """Table 3 from the evaluations of an ablation sweep (:func:`ablation_inputs`)."""
    table = write_ablation_report(ablation_inputs(cfg), Path(cfg.report.output_dir))
    show(table.read_text())
    intervals = table.with_name("table3_intervals.md")
    if intervals.is_file():
        show(intervals.read_text())
    return table


def require_held_out_cache(cfg: DictConfig) -> None:
    if cfg.evaluation.held_out_cache is None:
        raise ValueError(f"evaluation.held_out_cache: report.kind={cfg.report.kind} needs a prepared held-out cache "
                         "(tracegs-prepare data.prepare.split=test)")


def privileged_report(cfg: DictConfig) -> Path:
    """The privileged gap (eval/privileged.py): the frozen restorer A (the pseudo-target generator under the
    paper's data protocol), the Stage-2 student (this config's variant) and, with ``report.stage1_row``, the
    Stage-1 adapter restore the held-out clips from R_d and from R_s; ``privileged_gap.md`` and ``.json``."""
    require_held_out_cache(cfg)
    students = stage_table().per_variant()  # and the products they are made from
    locate_artifacts(cfg, stage_table().artifacts([*students.reads, students.product]))
    if not Path(cfg.artifacts.stage1_adapter).exists():
        raise FileNotFoundError(f"artifacts.stage1_adapter: no Stage-1 adapter at {cfg.artifacts.stage1_adapter} "
                                "(run tracegs-train stage=stage1 with the same settings)")
    pipelines = {name: restorer.pipeline for name, restorer in shared_restorers(
        section(cfg.backbone), cfg.artifacts.baseline_weights,
        {"baseline": None,
         **({STAGE1: AdapterFile(Path(cfg.artifacts.stage1_adapter), "artifacts.stage1_adapter", STAGE1,
                                 Product.stage1.value)} if cfg.report.stage1_row else {}),
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
    if len(cfg.report.inputs) < 2:
        raise ValueError("report.inputs: report.kind=seeds needs the folders of two or more demo runs")
    table = Path(cfg.report.output_dir) / "seeds.md"
    with atomic_write(table) as tmp:
        tmp.write_text(seed_spread_markdown(list(cfg.report.inputs)))
    show(table.read_text())
    return table


def per_step_report(cfg: DictConfig) -> Path:
    """Fig. 6 across variants (default: those of the paper's per-step claims, on-policy F vs off-policy E and
    A) on the clips of a prepared cache, with each variant's final restoration scored against its input R_s
    (``held_out_clips.md``); beside Fig. 6, the curves over the unpadded and the padded clips apart and at K = 3
    alone, with the capture-order rule of the clips (``per_step_breakdown.{md,json}``).

    Any split's cache works: the test split's held-out clips, or the validation split's
    (``tracegs-prepare data.prepare.split=val``), on which the embedded default's settings are chosen.
    """
    require_held_out_cache(cfg)
    pipelines = {}
    for variant in list(cfg.report.inputs) or per_step_variants(ConfigTree.of(cfg)):
        # Each variant's own config says which restorer stands for it and where its student adapter is.
        variant_cfg = as_variant(cfg, variant)
        method = variant_cfg.ablation.method
        pipelines[variant] = restorers_for_run(variant_cfg, [method])[method].pipeline
    clip_curves = held_out_clip_curves(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                       progress=cfg.evaluation.progress)
    units = unit_curves(clip_curves)
    curves = view_averaged_curves(units)  # Fig. 6: averaged across view settings
    out = Path(cfg.report.output_dir)
    write_json_atomic(curves, out / "per_step_variants.json")
    breakdown = per_step_breakdown(clip_curves)
    write_json_atomic(breakdown, out / "per_step_breakdown.json")
    with atomic_write(out / "per_step_breakdown.md") as tmp:
        tmp.write_text(per_step_breakdown_markdown(breakdown))
    bands = write_per_step_intervals(units, out, "per_step_variants", pairs=list(PER_STEP_PAIRS))
    figure = plot_per_step_quality(curves, out / "fig6_per_step_variants.png", bands=bands)
    for variant, curve in curves.items():
        show(f"{variant}: " + " ".join(f"{value:.2f}" for value in curve))
    show((out / "per_step_breakdown.md").read_text())
    quality = clip_restoration_psnr(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                    progress=cfg.evaluation.progress)
    show(write_held_out_report(quality, out).read_text())
    return figure
