"""Reverse-diffusion restoration of rendered clips (main paper Eq. 1; deployment, supplement A.4)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from rich.progress import track

from . import adapters
from .build import Backbone
from .schedules import NoiseSchedule
from .transformer import ReferenceGuidedTransformer


def guided_velocity(
    model: ReferenceGuidedTransformer,
    z: torch.Tensor,
    cond: torch.Tensor,
    t: torch.Tensor,
    text: torch.Tensor,
    ref_2d: torch.Tensor,
    ref_3d: torch.Tensor,
    guidance_scale: float,
) -> torch.Tensor:
    """Classifier-free guidance v_u + s (v_c - v_u), the unconditional branch using the all-zero text
    embedding (supplement A.2). Scale 1 is exactly the conditional velocity, so that pass is skipped."""
    if guidance_scale == 1.0:
        return model(noisy=z, cond=cond, timestep=t, text=text, ref_2d=ref_2d, ref_3d=ref_3d).velocity

    def twice(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, x])

    both = model(
        noisy=twice(z),
        cond=twice(cond),
        timestep=twice(t),
        text=torch.cat([text, torch.zeros_like(text)]),
        ref_2d=twice(ref_2d),
        ref_3d=twice(ref_3d),
    )
    conditional, unconditional = both.velocity.chunk(2)
    return unconditional + guidance_scale * (conditional - unconditional)


@torch.no_grad()
def sample(
    model: ReferenceGuidedTransformer,
    schedule: NoiseSchedule,
    cond: torch.Tensor,
    ref_2d: torch.Tensor,
    ref_3d: torch.Tensor,
    text: torch.Tensor,
    steps: int,
    guidance_scale: float,
    generator: torch.Generator,
    return_states: bool = False,
    progress: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
    """Run the M-step solver z_{t_M} ~ N(0, I) -> z_{t_0} conditioned on ``cond`` latents (B, f, C, h, w).

    Noise is drawn on the CPU from ``generator`` so a seed gives the same result on any device. bf16 autocast
    is used on CUDA. With ``return_states`` also returns the visited states [z_{t_M}, ..., z_{t_0}].
    """
    grid = schedule.timesteps(steps)
    batch = cond.shape[0]
    z = torch.randn(cond.shape, generator=generator, dtype=torch.float32).to(cond.device)
    states = [z]
    autocast = (
        torch.autocast("cuda", dtype=torch.bfloat16)
        if cond.device.type == "cuda"
        else contextlib.nullcontext()
    )
    pairs = list(zip(grid[:-1], grid[1:]))
    for t, t_prev in track(pairs, description="restoring", disable=not progress):
        t_batch = t.expand(batch).to(cond.device)
        with autocast:
            v = guided_velocity(model, z, cond, t_batch, text, ref_2d, ref_3d, guidance_scale)
        z = schedule.step(z, v.float(), t_batch, t_prev.expand(batch).to(cond.device))
        if return_states:
            states.append(z)
    return (z, states) if return_states else z


@contextlib.contextmanager
def using_adapter(model: ReferenceGuidedTransformer, adapter: str | None) -> Iterator[None]:
    """Run with the named adapter active, or with adapters disabled (the bare base) when ``adapter`` is None."""
    has_adapters = bool(adapters.adapter_names(model))
    if adapter is not None:
        previous = adapters.active_adapter(model)
        adapters.activate(model, adapter)
        try:
            yield
        finally:
            adapters.activate(model, previous)
    elif has_adapters:
        model.disable_adapters()
        try:
            yield
        finally:
            model.enable_adapters()
    else:
        yield


class RestorationPipeline:
    """Encode a rendered clip, restore it with the frozen backbone (+ one adapter), decode (Alg. 1, Restore)."""

    def __init__(self, backbone: Backbone, adapter: str | None = None):
        if adapter is not None and adapter not in adapters.adapter_names(backbone.transformer):
            raise KeyError(f"adapter {adapter!r} is not loaded on the backbone")
        self.backbone = backbone
        self.adapter = adapter

    @property
    def device(self) -> torch.device:
        return next(self.backbone.transformer.parameters()).device

    @torch.no_grad()
    def restore(
        self,
        frames: torch.Tensor,
        ref_images: torch.Tensor,
        captions: list[str],
        seed: int | None = None,
        steps: int | None = None,
        guidance_scale: float | None = None,
        progress: bool = False,
    ) -> torch.Tensor:
        """frames (B, F, 3, H, W) in [0, 1] -> restored frames of the same shape (defaults from the config)."""
        bb = self.backbone
        if len(captions) != frames.shape[0]:
            raise ValueError(f"got {len(captions)} captions for a batch of {frames.shape[0]} clips")
        device = self.device
        ref_2d, ref_3d = bb.reference_encoder(ref_images.to(device))
        latents = self.restore_latents(
            bb.codec.encode(frames.to(device)),
            ref_2d,
            ref_3d,
            bb.text_encoder.encode(captions),
            seed,
            steps,
            guidance_scale,
            progress,
        )
        return bb.codec.decode(latents).to(frames.device)

    @torch.no_grad()
    def restore_latents(
        self,
        cond: torch.Tensor,
        ref_2d: torch.Tensor,
        ref_3d: torch.Tensor,
        text: torch.Tensor,
        seed: int | None = None,
        steps: int | None = None,
        guidance_scale: float | None = None,
        progress: bool = False,
    ) -> torch.Tensor:
        """The same restoration from already encoded inputs (e.g. a prepared cache): clean latents."""
        cfg, device = self.backbone.cfg, self.device
        generator = torch.Generator().manual_seed(cfg.sampler.seed if seed is None else seed)
        with using_adapter(self.backbone.transformer, self.adapter):
            return sample(
                self.backbone.transformer,
                self.backbone.schedule,
                cond.to(device),
                ref_2d.to(device),
                ref_3d.to(device),
                text.to(device),
                steps or cfg.schedule.deploy_steps,
                cfg.sampler.guidance_scale if guidance_scale is None else guidance_scale,
                generator,
                progress=progress,
            )
