"""``tracegs-report report.kind=diagnostics``: the trajectory diagnostics of Table 3's variants on held-out clips.

For one training seed (this command line's settings), every variant in ``report.inputs`` (default: every
variant of conf/ablation/), and with ``report.stage1_row`` the Stage-1 adapter the students start from, is restored along its own deployment trajectory on the held-out clips, at the
student conditions of ``evaluation.views``: its per-step clean prediction (Fig. 6), the exposure gap and, for
the distilled variants, the advantage of their teacher (the Stage-1 adapter on the variant's R_d, Eq. 5) at the
student's states (tracegs.eval.diagnostics). All restorers share one backbone: A's weights, the Stage-1 adapter
and each student adapter loaded once.

Any split's prepared cache works: the test split's held-out clips (tracegs-replicate's), or the validation split's
(``tracegs-prepare data.prepare.split=val``), on which a schedule or Stage-2 budget that makes the trajectory
matter would be chosen. Its teacher conditions must cover the variants' (``data.prepare.dense_views``,
``data.prepare.student_final_fits``).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from tracegs.config.tree import ConfigTree
from tracegs.console import show
from tracegs.deploy.assembly import AdapterFile, shared_restorers
from tracegs.errors import ConfigError
from tracegs.eval.diagnostics import VariantRoles, held_out_diagnostics
from tracegs.eval.labels import STAGE1
from tracegs.eval.replicates import diagnostics_markdown
from tracegs.io import atomic_write, write_json_atomic
from tracegs.pipeline.upstream import as_variant, locate_artifacts, section
from tracegs.pipeline.variants import in_table_order, table3_variants
from tracegs.products import Product
from tracegs.stages import stage_table

TEACHER = STAGE1  # the adapter name of the frozen Stage-1 teacher on the shared backbone


def diagnostics_report(cfg: DictConfig) -> Path:
    """``diagnostics.json`` in ``report.output_dir`` (tracegs-replicate's report reads it); returns its path."""
    if cfg.evaluation.held_out_cache is None:
        raise ConfigError("evaluation.held_out_cache", "report.kind=diagnostics needs a prepared held-out cache "
                                                       "(tracegs-prepare data.prepare.split=test)")
    tree = ConfigTree.of(cfg)
    names = in_table_order(cfg.report.inputs, tree) if cfg.report.inputs else [v.name for v in table3_variants(tree)]
    unknown = sorted(set(cfg.report.inputs) - set(names))
    if unknown:
        raise ConfigError("report.inputs", f"{unknown} are not variants of conf/ablation/")
    variants = {name: as_variant(cfg, name) for name in names}
    distilled = any(variant.ablation.train_stage2 for variant in variants.values())
    if cfg.report.stage1_row and not distilled:
        raise ConfigError("report.stage1_row", "needs a distilled variant in report.inputs (A alone has no Stage-1 "
                                               "adapter)")
    # The students' inputs (A and the Stage-1 teacher); A alone needs A's weights only: a restorer design is judged
    # on its trajectory before any adapter exists.
    table = stage_table()
    students = table.per_variant()
    locate_artifacts(cfg, table.stage_inputs(students.product) if distilled else table.artifacts([Product.baseline]))
    files: dict[str, AdapterFile | None] = {TEACHER: None}
    if distilled:
        if not Path(cfg.artifacts.stage1_adapter).exists():
            raise FileNotFoundError(f"artifacts.stage1_adapter: no Stage-1 adapter at {cfg.artifacts.stage1_adapter} "
                                    "(run tracegs-train stage=stage1 with the same settings)")
        files[TEACHER] = AdapterFile(Path(cfg.artifacts.stage1_adapter), "artifacts.stage1_adapter", TEACHER,
                                     Product.stage1.value)
    roles = {}
    for name, variant in variants.items():
        if not variant.ablation.train_stage2:
            roles[name] = VariantRoles(student=None)
            continue
        locate_artifacts(variant, [students.artifact])
        student = Path(variant.artifacts.student_adapter)
        if not student.exists():
            raise FileNotFoundError(f"artifacts.student_adapter: no student adapter at {student} (run "
                                    f"tracegs-train stage=stage2 ablation={name} with the same settings)")
        files[name] = AdapterFile(student, "artifacts.student_adapter", name)
        roles[name] = VariantRoles(student=name, teacher=TEACHER, teacher_views=variant.teacher.views, distilled=True)
    if cfg.report.stage1_row:
        roles = {TEACHER: VariantRoles(student=TEACHER), **roles}
    restorers = shared_restorers(section(cfg.backbone), cfg.artifacts.baseline_weights, files,
                                 batch=cfg.deploy.clip_batch, steps=cfg.deploy.steps)
    result = held_out_diagnostics(restorers[TEACHER].pipeline.backbone, roles, cfg.evaluation.held_out_cache,
                                  student_views=list(cfg.evaluation.views), seed=cfg.deploy.seed,
                                  steps=cfg.deploy.steps, progress=cfg.evaluation.progress,
                                  workers=cfg.evaluation.workers)
    path = Path(cfg.report.output_dir) / "diagnostics.json"
    write_json_atomic(result, path)
    summary = diagnostics_markdown(result, list(roles), start=TEACHER if cfg.report.stage1_row else None)
    with atomic_write(path.with_suffix(".md")) as tmp:
        tmp.write_text(summary)
    show(summary)
    return path
