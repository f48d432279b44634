"""The pipeline's steps, declared once: prepare (training and held-out clips) -> A -> Stage 1 -> Stage 2 ->
evaluate -> report. ``tracegs-demo`` runs them in its own process; ``tracegs-benchmark`` runs them as child
commands, the restorer's steps once per training seed. Each caller adds only the overrides of its own setting.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

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


def data_steps(common: Sequence[str] = (), training: Sequence[str] = (), held_out: Sequence[str] = ()) -> list[Step]:
    """Prepare the training clips, then the test scenes' held-out clips."""
    return [Step("prepare", (*common, *training), "prepare (training scenes)"),
            Step("prepare", (*common, HELD_OUT_SPLIT, *held_out), "prepare (held-out test scenes)")]


def restorer_steps(variant: str, common: Sequence[str] = (), evaluation: Sequence[str] = (),
                   privileged: Sequence[str] | None = None) -> list[Step]:
    """Train A, the Stage-1 adapter and ``variant``'s Stage-2 student, then deploy and evaluate them; with
    ``privileged`` (the report's overrides), measure the student's privileged gap as well."""
    chosen = f"ablation={variant}"
    steps = [Step("train", (*common, "stage=baseline"), "train A"),
             Step("train", (*common, "stage=stage1"), "train Stage 1"),
             Step("train", (*common, "stage=stage2", chosen), "train Stage 2"),
             Step("evaluate", (*common, chosen, *evaluation), "evaluate")]
    if privileged is not None:
        steps.append(Step("report", (*common, chosen, "report.kind=privileged", *privileged), "privileged gap"))
    return steps


def out_of_domain_steps(variant: str, datasets: Sequence[str], common: Sequence[str] = (),
                        evaluation: Sequence[str] = ()) -> list[Step]:
    """Evaluate ``variant``'s restorers, trained on the training data (``training_data``), on each of ``datasets``
    (``data=<name>``, e.g. Mip-NeRF 360): paper Table 2, and Table 3's out-of-domain columns (report.datasets)."""
    return [Step("evaluate", (*common, f"ablation={variant}", f"data={dataset}", *evaluation), f"evaluate on {dataset}")
            for dataset in datasets]
