"""3DGS optimisation with snapshots and a weighted pseudo-observation term (supplement Eq. for L_3DGS(j))."""

from __future__ import annotations

import ctypes
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import kornia
import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import remove, reset_opa
from rich.progress import Progress
from torch import Tensor

from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig, PseudoSsim
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import fit_device, render, require_available


@dataclass
class View:
    """A posed image: `image` [3,H,W] in [0,1] seen by `camera`. A captured view's image is its camera's size; a
    pseudo view's may be another (a restored frame at the restorer's clip size, ``deploy.resolution=dataset``),
    which the loss compares with the render resized to it (``GaussianFitter._render``)."""

    image: Tensor
    camera: Camera

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[0] != 3:
            raise ValueError(f"View.image must have shape (3, H, W), got {tuple(self.image.shape)}")


def camera_extent(cameras: Sequence[Camera]) -> float:
    """3DGS scene scale: 1.1 x the largest distance of a camera centre from the centres' mean."""
    centres = torch.stack([camera.center for camera in cameras])
    radius = (centres - centres.mean(dim=0)).norm(dim=1).max().item() * 1.1
    return radius if radius > 0 else 1.0


def mean_ssim(rendered: Tensor, target: Tensor, window: int = 11) -> Tensor:
    """Mean SSIM of two [C,H,W] images: kornia's `metrics.ssim` (Gaussian window, sigma 1.5, reflect padding,
    c1 = 0.01^2, c2 = 0.03^2, eps 1e-12), equal to it to rounding.

    The five local moments are blurred in one call of kornia's separable filter on a stacked image, where
    `kornia.metrics.ssim` filters each moment apart: at the embedded 48 x 72 images the ten small convolutions
    and their backward cost more than the rasterizer, and stacking halves the loss's share of a 3DGS step.
    """
    kernel = kornia.filters.get_gaussian_kernel1d(window, 1.5, device=rendered.device, dtype=rendered.dtype)
    channels = rendered.shape[0]
    moments = torch.cat([rendered, target, rendered * rendered, target * target, rendered * target])[None]
    blurred = kornia.filters.filter2d_separable(moments, kernel, kernel, border_type="reflect")[0]
    mu1, mu2, mean11, mean22, mean12 = blurred.split(channels)
    mu12, mu1_sq, mu2_sq = mu1 * mu2, mu1 * mu1, mu2 * mu2
    c1, c2 = 0.01**2, 0.03**2
    numerator = (2.0 * mu12 + c1) * (2.0 * (mean12 - mu12) + c2)
    denominator = (mu1_sq + mu2_sq + c1) * ((mean11 - mu1_sq) + (mean22 - mu2_sq) + c2)
    return (numerator / (denominator + 1e-12)).mean()


def photometric_loss(rendered: Tensor, target: Tensor, ssim_weight: float, window: int = 11) -> Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM), the 3DGS reconstruction loss (lambda = 0.2)."""
    l1 = (rendered - target).abs().mean()
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - mean_ssim(rendered, target, window))


def _merge_infos(infos: list[dict]) -> dict:
    """One densification record for several renders of the same step.

    gsplat normally sees one batched render whose loss averages the cameras (hence its `n_cameras` factor);
    here each render's loss is summed, so the stacked gradients keep `n_cameras` = 1.
    """
    if len(infos) == 1:
        return infos[0]
    means2d = torch.cat([info["means2d"].detach() for info in infos])
    means2d.grad = torch.cat([info["means2d"].grad for info in infos])
    return {"means2d": means2d, "radii": torch.cat([info["radii"] for info in infos]), "width": infos[0]["width"],
            "height": infos[0]["height"], "n_cameras": 1, "gaussian_ids": None}


class _ViewSampler:
    """3DGS-style sampling: a fresh random permutation of the views each time the previous one is used up."""

    def __init__(self, generator: torch.Generator):
        self.generator = generator
        self.queue: list[int] = []
        self.size = -1

    def next(self, size: int) -> int:
        if size != self.size or not self.queue:
            self.size = size
            self.queue = torch.randperm(size, generator=self.generator).tolist()
        return self.queue.pop()


def keep_freed_cpu_memory() -> None:
    """Ask glibc to keep freed memory instead of returning it to the kernel.

    Every optimisation step allocates and frees tens of MB of temporaries; by default glibc maps and unmaps
    them each time, and the resulting page faults cost ~20% of a CPU step at the embedded scale (measured:
    ~2200 faults and 5 ms of system time per step). Holding on to the freed pages (the process keeps its peak
    footprint) is what torch's CUDA caching allocator does on GPU. No-op outside glibc.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    libc.mallopt(m_mmap_threshold, 1 << 30)
    libc.mallopt(m_trim_threshold, (1 << 31) - 1)


class GaussianFitter:
    """Runtime state of one 3DGS optimisation (model, Adam optimisers, densification state, iteration).

    Deep-copyable, so deployment can branch from a cold start.
    """

    PARAMETER_LRS = {"quats": "lr_quats", "scales": "lr_scales", "opacities": "lr_opacities", "sh0": "lr_sh_dc",
                     "shN": "lr_sh_rest"}

    def __init__(self, model: GaussianModel, cfg: GaussianFitConfig, scene_extent: float):
        if scene_extent <= 0:
            raise ValueError(f"scene_extent must be positive, got {scene_extent}")
        require_available(cfg.backend, "fit.backend")
        # 3DGS runs where the backend does: CUDA with gsplat's rasterizer when present, else the CPU.
        self.model = model.to(fit_device(cfg))
        self.cfg = cfg
        self.scene_extent = scene_extent
        self.iteration = 0
        params = model.parameter_dict()
        self.optimizers = {
            name: torch.optim.Adam([param], lr=self._initial_lr(name), eps=1e-15, fused=True)
            for name, param in params.items()
        }
        dens = cfg.densification
        # gsplat's DefaultStrategy runs on CPU tensors (only its rasterizer needs CUDA).
        self.strategy = DefaultStrategy(
            prune_opa=dens.prune_opa, grow_grad2d=dens.grow_grad2d, grow_scale3d=dens.grow_scale3d,
            prune_scale3d=dens.prune_scale3d, refine_start_iter=dens.refine_start_iter,
            refine_stop_iter=dens.refine_stop_iter if dens.enabled else 0, reset_every=dens.reset_every,
            refine_every=dens.refine_every,
            # Screen pruning (``screen_prune_px``) tracks radii; gsplat's split by screen size, which the reference
            # optimiser does not have, stays off.
            refine_scale2d_stop_iter=dens.refine_stop_iter if dens.screen_prune_px is not None else 0,
            grow_scale2d=math.inf,
        )
        self.strategy.check_sanity(params, self.optimizers)
        self.strategy_state = self.strategy.initialize_state(scene_scale=scene_extent)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.captured_sampler = _ViewSampler(self.generator)
        self.pseudo_sampler = _ViewSampler(self.generator)
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=model.means.device)
        if cfg.keep_freed_cpu_memory and model.means.device.type == "cpu":
            keep_freed_cpu_memory()

    def _initial_lr(self, name: str) -> float:
        return self.means_lr(0) if name == "means" else getattr(self.cfg, self.PARAMETER_LRS[name])

    def means_lr(self, step: int) -> float:
        """Exponential decay from lr_means to lr_means_final over cfg.iterations, times the scene extent."""
        progress = min(max(step / max(self.cfg.iterations, 1), 0.0), 1.0)
        log_lr = (1 - progress) * math.log(self.cfg.lr_means) + progress * math.log(self.cfg.lr_means_final)
        return math.exp(log_lr) * self.scene_extent

    def sh_degree(self, step: int) -> int:
        return self.cfg.sh_degree_at(step)

    def _render(self, view: View, step: int) -> tuple[Tensor, Tensor, dict]:
        """(render, target image, render info) of ``view``; a render of another size than its image (a restored
        frame at the clip's size) is resized to it bilinearly, as GSFixer's release does (train.py l. 204-208)."""
        camera = view.camera.to(self.model.means.device)
        out = render(self.model, camera, self.background, self.sh_degree(step), self.cfg.backend)
        image = view.image.to(out.image)
        rendered = out.image
        if rendered.shape != image.shape:
            rendered = torch.nn.functional.interpolate(rendered[None], size=image.shape[-2:], mode="bilinear")[0]
        return rendered, image, out.info

    def _render_loss(self, view: View, step: int) -> tuple[Tensor, dict]:
        rendered, image, info = self._render(view, step)
        return photometric_loss(rendered, image, self.cfg.ssim_weight, self.cfg.ssim_window), info

    def _losses(self, captured: View, pseudo: View | None, step: int) -> tuple[Tensor, Tensor | None, list[dict]]:
        """(L_sparse, L_pseudo or None, the render infos densification reads). With ``pseudo_ssim=captured`` the
        pseudo term is (1 - lambda) L1(pseudo) + lambda (1 - SSIM(captured render, captured image)), GSFixer's
        train.py l. 210-213; with ``pseudo_densification`` false only the captured render's info is kept
        (l. 198-202, 243)."""
        weight, window = self.cfg.ssim_weight, self.cfg.ssim_window
        if pseudo is None or self.cfg.pseudo_ssim == PseudoSsim.pseudo:
            loss, info = self._render_loss(captured, step)
            pseudo_loss, pseudo_info = (None, None) if pseudo is None else self._render_loss(pseudo, step)
        else:
            rendered, image, info = self._render(captured, step)
            captured_dssim = 1.0 - mean_ssim(rendered, image, window)
            loss = (1.0 - weight) * (rendered - image).abs().mean() + weight * captured_dssim
            rendered, image, pseudo_info = self._render(pseudo, step)
            pseudo_loss = (1.0 - weight) * (rendered - image).abs().mean() + weight * captured_dssim
        infos = [info] if pseudo_info is None or not self.cfg.pseudo_densification else [info, pseudo_info]
        return loss, pseudo_loss, infos

    def step(self, captured: Sequence[View], pseudo: Sequence[View] = (),
             pseudo_weight: Callable[[int], float] | None = None) -> float:
        """One optimisation step j = self.iteration: L_sparse + w(j) L_pseudo (w = 1 without a schedule)."""
        step = self.iteration
        params = self.model.parameter_dict()
        weight = 0.0
        if pseudo:
            weight = 1.0 if pseudo_weight is None else float(pseudo_weight(step))
        view = captured[self.captured_sampler.next(len(captured))]
        pseudo_view = pseudo[self.pseudo_sampler.next(len(pseudo))] if weight > 0.0 else None
        loss, pseudo_loss, infos = self._losses(view, pseudo_view, step)
        if pseudo_loss is not None:
            loss = loss + weight * pseudo_loss
        for info in infos:
            self.strategy.step_pre_backward(params, self.optimizers, self.strategy_state, step, info)
        loss.backward()

        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr(step)
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        dens = self.cfg.densification
        if dens.enabled and all(info["means2d"].grad is not None for info in infos):
            # gsplat's split draws from the global RNG; seed it from the fitter's generator so a run (and a
            # deep-copied branch of it) is reproducible without disturbing anyone else's random stream.
            seed = int(torch.randint(2**62, (), generator=self.generator))
            with torch.random.fork_rng(devices=[]):
                # The generator of the model's device only: torch.manual_seed would also queue a seeding call
                # (with a captured stack trace) for every uninitialised accelerator, each step (~10% of a CPU fit).
                torch.default_generator.manual_seed(seed)
                if self.model.means.is_cuda:
                    torch.cuda.manual_seed_all(seed)
                merged = _merge_infos(infos)
                if dens.screen_prune_px is not None:  # gsplat's radii are in units of the larger image side
                    self.strategy.prune_scale2d = dens.screen_prune_px / max(merged["width"], merged["height"])
                self.strategy.step_post_backward(params, self.optimizers, self.strategy_state, step, merged)
            if step > 0 and step % dens.reset_every == 0 and step < dens.refine_stop_iter:
                # gsplat 1.5.3 writes `step % reset_every == 0 & step > 0`, which Python chains into a
                # condition that is never true, so its opacity reset never runs; apply it here (idempotent if a
                # fixed gsplat also resets).
                reset_opa(params, self.optimizers, self.strategy_state, value=dens.prune_opa * 2.0)
            excess = 0 if dens.max_gaussians is None else len(params["means"]) - dens.max_gaussians
            if excess > 0:
                # A budget that gsplat's strategy does not have: drop the least opaque Gaussians.
                weakest = params["opacities"].detach().argsort()[:excess]
                mask = torch.zeros(len(params["means"]), dtype=torch.bool, device=weakest.device)
                mask[weakest] = True
                remove(params, self.optimizers, self.strategy_state, mask)
            self.model.load_parameter_dict(params)
        self.iteration += 1
        return loss.item()

    def train_until(self, until: int, captured: Sequence[View], pseudo: Sequence[View] = (),
                    pseudo_weight: Callable[[int], float] | None = None,
                    on_snapshot: Callable[[int, GaussianModel], None] | None = None,
                    progress: bool = True) -> dict[str, float]:
        """Optimise from `self.iteration` up to `until` iterations; `on_snapshot(iteration, model)` fires after
        every iteration listed in cfg.snapshot_iters. Returns the mean loss and the model size."""
        if not captured:
            raise ValueError("train_until needs at least one captured view")
        losses = []
        with Progress(disable=not progress, transient=True) as bar:
            task = bar.add_task("3DGS", total=max(until - self.iteration, 0))
            while self.iteration < until:
                losses.append(self.step(captured, pseudo, pseudo_weight))
                if on_snapshot is not None and self.iteration in self.cfg.snapshot_iters:
                    on_snapshot(self.iteration, self.model)
                bar.advance(task)
        return {"loss": sum(losses) / len(losses) if losses else float("nan"),
                "final_loss": losses[-1] if losses else float("nan"),
                "num_gaussians": float(len(self.model)), "iteration": float(self.iteration)}


def random_initial_model(views: Sequence[View], cfg: GaussianFitConfig) -> GaussianModel:
    """Random Gaussians in the region the cameras look at (when no SfM points are given)."""
    from tracegs.splat.trajectory import focus_point

    cameras = [view.camera for view in views]
    centre = focus_point(cameras)
    radius = 0.5 * min((camera.center - centre).norm().item() for camera in cameras)
    generator = torch.Generator().manual_seed(cfg.seed)
    return GaussianModel.random(cfg.init_num_points, center=centre, radius=radius, generator=generator)


def fit_gaussians(views: Sequence[View], cfg: GaussianFitConfig, init: GaussianModel | None = None,
                  snapshots: Sequence[int] | None = None, progress: bool = False) -> dict[int, GaussianModel]:
    """Fit a 3DGS to `views`; returns copies of the model after each snapshot iteration (default
    cfg.snapshot_iters and cfg.iterations). The schedules (lr decay, densification) always span
    cfg.iterations, so a fit that stops at its last wanted snapshot gives the same snapshots as a longer one."""
    wanted = sorted(set(cfg.snapshot_iters) | {cfg.iterations} if snapshots is None else set(snapshots))
    if not wanted or wanted[0] < 1 or wanted[-1] > cfg.iterations:
        raise ValueError(f"snapshot iterations must lie in [1, {cfg.iterations}], got {wanted}")
    run_cfg = replace(cfg, snapshot_iters=wanted)
    model = (init if init is not None else random_initial_model(views, cfg)).clone()
    fitter = GaussianFitter(model, run_cfg, camera_extent([view.camera for view in views]))
    results: dict[int, GaussianModel] = {}
    fitter.train_until(wanted[-1], views, on_snapshot=lambda it, m: results.__setitem__(it, m.clone()),
                       progress=progress)
    return results
