"""``DeploymentRefinement``: run the restore-refine loop with the restorer being trained, during training.

Every ``every_n_steps`` optimizer steps and at the end of training, the callback builds a restorer from the
LightningModule's current weights, deploys it on the validation scenes' sparse views (Algorithm 1 bottom) and
logs PSNR/SSIM(/LPIPS) on their test views to the trainer's loggers, so one sees whether restorer training
improves the downstream 3DGS and not only its own loss.

The sparse-only cold starts do not depend on the restorer, so they are fitted once and reused. Deployment runs
on its own random streams (the caller's are restored afterwards), so a run trains the same weights with the
callback as without it. Under DDP only rank 0 deploys (the weights are the same on every rank) while the
others wait at a barrier; the wait must fit in the process group's timeout.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import lightning as L
import torch

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.deploy.config import RefinementConfig
from tracegs.deploy.refine import refine
from tracegs.deploy.restorers import ClipRestorer, DiffusionRestorer
from tracegs.deploy.scenes import SceneUnit, deployment_source, load_unit
from tracegs.eval.metrics import METRIC_NAMES, ImageMetrics, mean_metrics
from tracegs.restorer.build import with_encoders
from tracegs.restorer.sampler import RestorationPipeline
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter

RestorerFactory = Callable[[L.LightningModule], ClipRestorer]


class ModuleRestorerFactory:
    """Restores with the module's *own* transformer (``pl_module.transformer``, shared, not copied) and the frozen
    codec / encoders / schedule of ``backbone`` (``restorer.build.Backbone``; one built for training, without
    encoders, gets them on first use, on the module's device). ``adapter`` names the LoRA adapter to deploy
    (``"student"`` in Stage 2; None = the bare base). A class, not a closure: spawned ranks receive it pickled."""

    def __init__(self, backbone, adapter: str | None, clip_batch: int = 4, steps: int | None = None):
        self.backbone, self.adapter, self.clip_batch, self.steps = backbone, adapter, clip_batch, steps

    def __call__(self, pl_module: L.LightningModule) -> ClipRestorer:
        self.backbone = with_encoders(self.backbone, pl_module.device)
        live = dataclasses.replace(self.backbone, transformer=pl_module.transformer)
        return DiffusionRestorer(RestorationPipeline(live, adapter=self.adapter), self.clip_batch, steps=self.steps)


class DeploymentRefinement(L.Callback):
    """Deploy the in-training restorer on validation scenes and log the metrics (``<prefix>/psnr_k3`` ...).

    ``restorer_factory(pl_module)`` returns a ``ClipRestorer`` around the module's current weights (e.g. a
    ``DiffusionRestorer`` whose pipeline shares the module's transformer and student adapter).
    """

    def __init__(self, scenes: Sequence[str], source: SceneSourceConfig, restorer_factory: RestorerFactory,
                 refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig, views: Sequence[int] = (3,),
                 every_n_steps: int | None = None, lpips: bool = False, prefix: str = "deploy"):
        super().__init__()
        if not scenes:
            raise ValueError("DeploymentRefinement needs at least one validation scene")
        if every_n_steps is not None and every_n_steps < 1:
            raise ValueError(f"every_n_steps must be >= 1 or None, got {every_n_steps}")
        refine_cfg.validate()
        self.scenes, self.views = list(scenes), [int(v) for v in views]
        self.source = deployment_source(source, refine_cfg)
        self.restorer_factory = restorer_factory
        self.refine_cfg, self.fit_cfg = refine_cfg, fit_cfg
        self.every_n_steps = every_n_steps
        self.lpips = lpips
        self.prefix = prefix
        self.history: list[dict] = []
        self._metrics: ImageMetrics | None = None
        self._units: list[tuple[SceneUnit, GaussianFitter]] | None = None
        self._deployed_step: int | None = None

    def _prepared_units(self) -> list[tuple[SceneUnit, GaussianFitter]]:
        if self._units is None:
            self._units = []
            for name in self.scenes:
                scene = load_scene(self.source, name)
                for k in self.views:
                    unit = load_unit(scene, k, self.source)
                    self._units.append((unit, unit.cold_start(self.refine_cfg, self.fit_cfg)))
        return self._units

    def run(self, pl_module: L.LightningModule) -> dict[str, float]:
        """Deploy once with the module's current weights; returns the metric values."""
        was_training = pl_module.training
        pl_module.eval()
        # Deployment seeds torch's global generator (refine.py): fork it so training continues on its own stream.
        # Lightning may call in inference mode, but 3DGS optimisation needs autograd: leave it for the deployment.
        devices = [pl_module.device] if pl_module.device.type == "cuda" else []
        try:
            with torch.random.fork_rng(devices=devices), torch.inference_mode(False), torch.enable_grad():
                per_k = self._deploy(self.restorer_factory(pl_module))
        finally:
            pl_module.train(was_training)
        logged = {}
        for k, scene_means in per_k.items():
            mean = mean_metrics(scene_means)
            for name in METRIC_NAMES:
                if mean[name] is not None:
                    logged[f"{self.prefix}/{name}_k{k}"] = mean[name]
        return logged

    def _deploy(self, restorer: ClipRestorer) -> dict[int, list[dict]]:
        if self._metrics is None:
            self._metrics = ImageMetrics(lpips=self.lpips)
        background = torch.tensor(self.fit_cfg.background, dtype=torch.float32)
        per_k: dict[int, list[dict]] = {k: [] for k in self.views}
        for unit, cold in self._prepared_units():
            model = refine(cold, unit.captured, restorer, self.refine_cfg, self.fit_cfg,
                           caption=unit.scene.caption or "")
            renders = unit.render_tests(model, background)
            per_k[unit.views].append(mean_metrics(self._metrics.per_view(renders, unit.test_images)))
        return per_k

    def deploy_and_log(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Rank 0 deploys and writes the scores to every logger at the current step; the other ranks wait.

        Every rank calls this at the same step (the schedule depends on the global step only), so each reaches
        the barrier once; a rank-0 failure ends the job through Lightning's launcher rather than leaving the
        others waiting."""
        step = trainer.global_step
        if step == self._deployed_step:
            return
        self._deployed_step = step
        if trainer.is_global_zero:
            logged = self.run(pl_module)
            self.history.append({"step": step, **logged})
            for logger in trainer.loggers:
                logger.log_metrics(logged, step=step)
                logger.save()
        trainer.strategy.barrier("deployment_eval")

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        if self.every_n_steps is not None and trainer.global_step % self.every_n_steps == 0:
            self.deploy_and_log(trainer, pl_module)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.deploy_and_log(trainer, pl_module)
