"""The privileged gap on held-out clips: how much better a restorer does from the teacher's condition.

Stage 2 distils a teacher that sees R_d, the render of a 3DGS fitted to the privileged view set (main paper
Sec. 3, the teacher of Eq. 6-7), into a student that sees only R_s. Distillation can only transfer what the
privileged condition adds: if restoring from R_d is no closer to ground truth than restoring from R_s, there is
little to distil at this scale. For every held-out clip each restorer (A, the Stage-1 adapter, the Stage-2
student) restores both its R_d and each student condition R_s (K views, snapshot) with the same noise seed;
each output is scored against ground truth and against R_d itself (how close the student gets to the
teacher's input). Reference frames are excluded and scene means come first, as in ``tracegs.eval.clips``.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from rich.progress import track

from tracegs.data import cache_keys
from tracegs.data.cache_keys import condition_key
from tracegs.eval.clips import held_out_clips, load_clip, mean_psnr, restore_clip, trajectory_frames
from tracegs.eval.intervals import Interval, mean_interval, paired_interval
from tracegs.eval.labels import RESTORER_LABELS, STAGE1
from tracegs.restorer.sampler import RestorationPipeline

TEACHER, STUDENT = "R_d", "R_s"
REFERENCES = ("gt", TEACHER)  # scored against ground truth and against the teacher's condition


@torch.no_grad()
def privileged_gap(pipelines: Mapping[str, RestorationPipeline], cache_dir: str | Path,
                   teacher_views: int | None = None, student_views: Sequence[int] | None = None, seed: int = 0,
                   progress: bool = True) -> dict:
    """PSNR (dB) of each restorer's output from R_d and from R_s, against ground truth and against R_d.

    ``student_views`` keeps the student conditions of those view counts (None = every condition cached): each
    condition is one more clip to restore per restorer.

    Returns ``{"per_scene": {scene: {row: {"gt": psnr, "R_d": psnr}}}, "rows": [...], "teacher": key,
    "clips": n}`` where a row is ``"input R_d"``, ``"input R_s"`` or ``"<label> | R_d"`` / ``"<label> | R_s"``;
    R_s rows average the student conditions of a clip (those of its own student view count K).
    """
    shards = held_out_clips(cache_dir)
    if student_views is not None:
        shards = [clip for clip in shards if clip.views in student_views]
        if not shards:
            raise ValueError(f"{cache_dir}: no student condition at {list(student_views)} views")
    teacher = condition_key(teacher_views)
    # scores[row][reference][scene] -> one value per clip
    scores: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))

    def record(row: str, scene: str, frames: list[torch.Tensor], truth: torch.Tensor,
               dense: torch.Tensor | None) -> None:
        """``dense=None``: score against ground truth only (R_d against itself is no measurement)."""
        for reference, target in zip(REFERENCES, (truth, dense)):
            if target is not None:
                scores[row][reference][scene].append(sum(mean_psnr(f, target) for f in frames) / len(frames))

    for index, clip in enumerate(track(shards, description="privileged gap", disable=not progress)):
        scene, conditions = clip.scene, clip.conditions()
        keys = [teacher, *conditions]
        if cache_keys.latent(teacher) not in clip.keys:
            raise KeyError(f"{clip.path}: no teacher condition {teacher} (prepare with data.prepare.dense_views "
                           "including the teacher's views)")
        tensors = load_clip(clip)
        truth, dense = trajectory_frames(tensors, cache_keys.GROUND_TRUTH), trajectory_frames(tensors, teacher)
        record(f"input {TEACHER}", scene, [dense], truth, None)
        record(f"input {STUDENT}", scene, [trajectory_frames(tensors, c) for c in conditions], truth, dense)
        for label, pipeline in pipelines.items():
            restored = restore_clip(pipeline, tensors, keys, seed + index)
            record(f"{label} | {TEACHER}", scene, [restored[0]], truth, dense)
            record(f"{label} | {STUDENT}", scene, list(restored[1:]), truth, dense)
    scenes = sorted({clip.scene for clip in shards})
    return {
        "conditions": sorted({c for clip in shards for c in clip.conditions()}, key=cache_keys.student_order),
        "per_scene": {scene: {row: {ref: sum(v[scene]) / len(v[scene]) for ref, v in by_ref.items()}
                              for row, by_ref in scores.items()} for scene in scenes},
        "rows": list(scores),
        "teacher": teacher,
        "clips": len(shards),
    }


BASELINE = "baseline"
STUDENT_ROW = "tracegs"  # the Stage-2 student's row (tracegs.eval.labels)


def privileged_figures(gap: Mapping) -> dict[str, Interval]:
    """With variant A among the restorers: A from R_s - input R_s, the privileged gap A from R_d - A from R_s, and
    each other restorer from R_s - A from R_s and - A from R_d, and with both students the Stage-2 student from R_s -
    the Stage-1 adapter from R_s (paired by scene, against ground truth, 95% bootstrap intervals over scenes); empty
    without A. Keys name the differences."""
    per_scene = gap["per_scene"]
    if f"{BASELINE} | {STUDENT}" not in gap["rows"]:
        return {}

    def truth(row: str) -> dict[str, float]:
        return {scene: rows[row]["gt"] for scene, rows in per_scene.items()}

    a_sparse, a_dense = truth(f"{BASELINE} | {STUDENT}"), truth(f"{BASELINE} | {TEACHER}")
    figures = {"A from R_s - input R_s": paired_interval(a_sparse, truth(f"input {STUDENT}")),
               "A from R_d - A from R_s (privileged gap)": paired_interval(a_dense, a_sparse)}
    for row in gap["rows"]:
        label, _, condition = row.partition(" | ")
        if condition == STUDENT and label != BASELINE:
            name = RESTORER_LABELS.get(label, label)
            figures[f"{name} from R_s - A from R_s"] = paired_interval(truth(row), a_sparse)
            figures[f"{name} from R_s - A from R_d"] = paired_interval(truth(row), a_dense)
    # Whether Stage 2 leaves the student above or below where Stage 1 started it (a collapse shows here first).
    student, start = f"{STUDENT_ROW} | {STUDENT}", f"{STAGE1} | {STUDENT}"
    if student in gap["rows"] and start in gap["rows"]:
        figures[f"{RESTORER_LABELS[STUDENT_ROW]} from R_s - {RESTORER_LABELS[STAGE1]} from R_s"] = paired_interval(
            truth(student), truth(start))
    return figures


def privileged_gap_markdown(gap: Mapping) -> str:
    """The gap table: each row against GT and against R_d (95% intervals over scenes), then per restorer the
    paired gap (output from R_d - output from R_s, same scenes) against ground truth."""
    per_scene = gap["per_scene"]
    first = next(iter(per_scene))

    def scores(row: str, reference: str) -> dict[str, float]:
        return {scene: rows[row][reference] for scene, rows in per_scene.items()}

    def name(row: str) -> str:
        label, _, condition = row.partition(" | ")
        return f"{RESTORER_LABELS.get(label, label)} from {condition}" if condition else row

    lines = [f"Held-out clips ({gap['clips']} clips of {len(per_scene)} scenes; R_d = teacher condition "
             f"{gap['teacher']}, R_s = mean over the student conditions {', '.join(gap['conditions'])}). PSNR (dB), "
             "95% bootstrap interval over scenes:", "", "| | vs ground truth | vs R_d |", "|---|---|---|"]
    for row in gap["rows"]:
        lines.append(f"| {name(row)} | " + " | ".join(
            mean_interval(list(scores(row, ref).values())).format() if ref in per_scene[first][row] else "—"
            for ref in REFERENCES) + " |")
    restorers = [row.partition(" | ")[0] for row in gap["rows"] if row.endswith(f"| {TEACHER}")]
    against_baseline = privileged_figures(gap)
    if against_baseline:
        lines += ["", "The frozen restorer A and the students (paired by scene, against ground truth): what A adds to "
                  "its input, the gap A's pseudo-targets carry (A from R_d - A from R_s: what Stage 2 can transfer), "
                  "and each student from R_s against A from R_s and from R_d:", "", "| difference | PSNR (dB) |",
                  "|---|---|"]
        lines += [f"| {label} | {interval.format(signed=True)} |" for label, interval in against_baseline.items()]
    lines += ["", "Privileged gap: the same restorer from R_d minus from R_s, against ground truth (paired by "
              "scene), and the input gap R_d - R_s:", "", "| restorer | gap vs ground truth |", "|---|---|"]
    lines.append("| input (no restoration) | " + paired_interval(
        scores(f"input {TEACHER}", "gt"), scores(f"input {STUDENT}", "gt")).format(signed=True) + " |")
    for label in restorers:
        lines.append(f"| {RESTORER_LABELS.get(label, label)} | " + paired_interval(
            scores(f"{label} | {TEACHER}", "gt"), scores(f"{label} | {STUDENT}", "gt")).format(signed=True) + " |")
    return "\n".join(lines) + "\n"
