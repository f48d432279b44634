"""``HeldOutClipQuality``: the restorer being trained, scored on held-out paired clips while it trains.

Stage 2's learning curve (main paper Sec. 3.4): before the first step (the student is then the Stage-1 adapter it
was cloned from; the bare base, variant A, is scored once beside it), every ``every_n_steps`` optimiser steps and
at the end, every clip of a held-out cache (e.g. the validation scenes', ``tracegs-prepare
data.prepare.split=val``) is restored from its student conditions R_s along the full deployment schedule and
scored against ground truth (``eval.clips.clip_restoration_psnr``). Each point keeps the mean over scenes and
each scene's value, so the curve is drawn with its 95% interval over scenes: ``held_out_curve.{json,png}`` in the
run folder, and the means go to the trainer's loggers (``held_out/psnr``).

Restoration draws from its own seeded generators, never from the training streams, so a run trains the same
weights with the callback as without it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import lightning as L
import torch

from tracegs.eval.clips import INPUT, clip_restoration_psnr
from tracegs.eval.intervals import mean_interval
from tracegs.eval.tables_and_figures import plot_per_step_quality
from tracegs.io import write_json_atomic
from tracegs.restorer.build import with_encoders
from tracegs.restorer.sampler import RestorationPipeline

BASE = "A"  # the bare base restorer (adapters off): variant A
INITIAL = "initial"  # the trained adapter before its first step (Stage 2: the Stage-1 adapter)
HELD_OUT_CURVE = "held_out_curve.json"  # in the run folder


class HeldOutClipQuality(L.Callback):
    """Score the module's ``adapter`` (on its own transformer) on the held-out clips of ``cache_dir``."""

    def __init__(self, backbone, adapter: str, cache_dir: str | Path, output_dir: str | Path,
                 every_n_steps: int, seed: int = 0):
        super().__init__()
        if every_n_steps < 1:
            raise ValueError(f"every_n_steps must be >= 1, got {every_n_steps}")
        self.backbone, self.adapter = backbone, adapter
        self.cache_dir, self.output_dir = Path(cache_dir), Path(output_dir)
        self.every_n_steps, self.seed = every_n_steps, seed
        self.points: list[dict] = []  # {"step", "mean", "per_scene"}
        self.references: dict[str, dict] = {}  # BASE / INPUT / INITIAL -> {"mean", "per_scene"}
        self._recorded_step: int | None = None  # on every rank, so all reach the barrier equally often

    def _score(self, pl_module: L.LightningModule, adapters: dict[str, str | None]) -> dict[str, dict]:
        self.backbone = with_encoders(self.backbone, pl_module.device)
        live = dataclasses.replace(self.backbone, transformer=pl_module.transformer)
        pipelines = {label: RestorationPipeline(live, adapter=name) for label, name in adapters.items()}
        was_training = pl_module.training
        pl_module.eval()
        try:
            with torch.random.fork_rng(devices=[]):
                scores = clip_restoration_psnr(pipelines, self.cache_dir, seed=self.seed, progress=False)
        finally:
            pl_module.train(was_training)
        return {label: {"mean": scores["mean"][label],
                        "per_scene": {scene: sum(by_cond[label] for by_cond in conditions.values()) / len(conditions)
                                      for scene, conditions in scores["per_scene"].items()}}
                for label in [INPUT, *adapters]}

    def _record(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        step = trainer.global_step
        if step == self._recorded_step:
            return
        self._recorded_step = step
        if trainer.is_global_zero:
            first = not self.points and step == 0
            labels = {BASE: None, INITIAL: self.adapter} if first else {self.adapter: self.adapter}
            scores = self._score(pl_module, labels)
            if first:
                self.references = {label: scores[label] for label in (INPUT, BASE, INITIAL)}
            self.points.append({"step": step, **scores[INITIAL if first else self.adapter]})
            for logger in trainer.loggers:
                logger.log_metrics({"held_out/psnr": self.points[-1]["mean"]}, step=step)
            self.write()
        trainer.strategy.barrier("held_out_eval")

    def write(self) -> None:
        """``held_out_curve.json`` and its plot: the adapter's mean over scenes per step with its 95% interval over
        scenes, and the input R_s, A and the initial adapter as constant lines."""
        record = {"adapter": self.adapter, "cache": self.cache_dir.name, "references": self.references,
                  "points": self.points}
        write_json_atomic(record, self.output_dir / HELD_OUT_CURVE)
        if not self.references:  # resumed past step 0: the lines of the reference restorers are unknown
            return
        steps = [p["step"] for p in self.points]
        intervals = [mean_interval(list(p["per_scene"].values())) for p in self.points]
        curves = {self.adapter: [p["mean"] for p in self.points],
                  **{label: [ref["mean"]] * len(steps) for label, ref in self.references.items()}}
        plot_per_step_quality(curves, self.output_dir / "held_out_curve.png", steps=steps,
                              xlabel="optimiser step", ylabel="PSNR (dB) of restored held-out clips",
                              title=f"{self.adapter} on {len(self.points[-1]['per_scene'])} held-out scenes' clips",
                              bands={self.adapter: ([i.low for i in intervals], [i.high for i in intervals])})

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._record(trainer, pl_module)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        if trainer.global_step % self.every_n_steps == 0:
            self._record(trainer, pl_module)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._record(trainer, pl_module)
