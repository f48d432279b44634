"""``DeploymentRefinement``: run the restore-refine loop with the restorer being trained, during training.

At chosen epochs (``every_n_epochs``) or after chosen global steps (``at_steps``), at the end of a
validation epoch, the callback builds a restorer from the LightningModule's current weights, deploys it on
the validation scenes' sparse views (Algorithm 1 bottom) and logs PSNR/SSIM/LPIPS on their test views,
so one sees whether restorer training improves the downstream 3DGS and not only its own loss.

The sparse-only cold starts do not depend on the restorer, so they are fitted once and reused.
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
from tracegs.deploy.scenes import SceneUnit, load_unit
from tracegs.eval.metrics import METRIC_NAMES, ImageMetrics, mean_metrics
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter
from tracegs.splat.render import render_views

RestorerFactory = Callable[[L.LightningModule], ClipRestorer]


def module_restorer_factory(backbone, adapter: str | None, clip_batch: int = 4,
                            steps: int | None = None) -> RestorerFactory:
    """A factory restoring with the module's *own* transformer (``pl_module.transformer``, shared, not
    copied) and the frozen codec / encoders / schedule of ``backbone`` (``restorer.build.Backbone``).
    ``adapter`` names the LoRA adapter to deploy (``"student"`` in Stage 2; None = the bare base)."""
    from tracegs.restorer.sampler import RestorationPipeline

    def factory(pl_module: L.LightningModule) -> ClipRestorer:
        live = dataclasses.replace(backbone, transformer=pl_module.transformer)
        return DiffusionRestorer(RestorationPipeline(live, adapter=adapter), clip_batch, steps=steps)

    return factory


class DeploymentRefinement(L.Callback):
    """Deploy the in-training restorer on validation scenes and log the metrics (``<prefix>/psnr_k3`` ...).

    ``restorer_factory(pl_module)`` returns a ``ClipRestorer`` around the module's current weights (e.g. a
    ``DiffusionRestorer`` whose pipeline shares the module's transformer and student adapter).
    """

    def __init__(self, scenes: Sequence[str], source: SceneSourceConfig, restorer_factory: RestorerFactory,
                 refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig, views: Sequence[int] = (3,),
                 every_n_epochs: int | None = 1, at_steps: Sequence[int] = (), lpips: bool = False,
                 prefix: str = "deploy"):
        super().__init__()
        if not scenes:
            raise ValueError("DeploymentRefinement needs at least one validation scene")
        if every_n_epochs is not None and every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1 or None, got {every_n_epochs}")
        refine_cfg.validate()
        self.scenes, self.source, self.views = list(scenes), source, [int(v) for v in views]
        self.restorer_factory = restorer_factory
        self.refine_cfg, self.fit_cfg = refine_cfg, fit_cfg
        self.every_n_epochs, self.pending_steps = every_n_epochs, sorted(at_steps)
        self.metrics = ImageMetrics(lpips=lpips)
        self.prefix = prefix
        self.history: list[dict] = []
        self._units: list[tuple[SceneUnit, GaussianFitter]] | None = None

    def _due(self, trainer: L.Trainer) -> bool:
        due = False
        while self.pending_steps and trainer.global_step >= self.pending_steps[0]:
            self.pending_steps.pop(0)
            due = True
        if self.every_n_epochs is not None and (trainer.current_epoch + 1) % self.every_n_epochs == 0:
            due = True
        return due

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
        """Deploy once with the module's current weights; returns the logged values."""
        was_training = pl_module.training
        pl_module.eval()
        # Lightning validates under inference mode, but 3DGS optimisation needs autograd, and tensors made
        # in inference mode cannot be saved for backward: leave it for the whole deployment.
        try:
            with torch.inference_mode(False), torch.enable_grad():
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
        background = torch.tensor(self.fit_cfg.background, dtype=torch.float32)
        per_k: dict[int, list[dict]] = {k: [] for k in self.views}
        for unit, cold in self._prepared_units():
            model = refine(cold, unit.captured, restorer, self.refine_cfg, self.fit_cfg,
                           caption=unit.scene.caption or "")
            renders = render_views(model, unit.test_cameras, background, None).cpu()
            per_k[unit.views].append(mean_metrics(self.metrics.per_view(renders, unit.test_images)))
        return per_k

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or not self._due(trainer):
            return
        logged = self.run(pl_module)
        self.history.append({"epoch": trainer.current_epoch, "step": trainer.global_step, **logged})
        pl_module.log_dict(logged, on_step=False, on_epoch=True, sync_dist=True)
