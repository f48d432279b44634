"""Reverse-diffusion restoration of rendered clips (main paper Eq. 1; deployment, supplement A.4)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch
from rich.progress import track

from tracegs.restorer import adapters
from tracegs.restorer.build import Backbone
from tracegs.restorer.schedules import NoiseSchedule
from tracegs.restorer.transformer import ReferenceGuidedTransformer, RestorerOutput


def guided_prediction(
    model: ReferenceGuidedTransformer,
    z: torch.Tensor,
    cond: torch.Tensor,
    t: torch.Tensor,
    text: torch.Tensor,
    ref_2d: torch.Tensor,
    ref_3d: torch.Tensor,
    guidance_scale: float,
    return_retrieval: bool = False,
    uncond_text: torch.Tensor | None = None,
) -> RestorerOutput:
    """One restorer evaluation under classifier-free guidance: velocity v_u + s (v_c - v_u), the unconditional
    branch using ``uncond_text`` (``negative_text``: one prompt's encoding, broadcast over the batch), None = the
    all-zero text embedding (supplement A.2). Scale 1 is exactly the conditional velocity, so that pass is
    skipped; otherwise both branches run as one doubled batch (twice the compute and activations).
    The retrieval response (main paper Eq. 7) is the conditional branch's."""
    if guidance_scale == 1.0:
        return model(noisy=z, cond=cond, timestep=t, text=text, ref_2d=ref_2d, ref_3d=ref_3d,
                     return_retrieval=return_retrieval)

    def twice(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, x])

    both = model(
        noisy=twice(z),
        cond=twice(cond),
        timestep=twice(t),
        text=torch.cat([text, torch.zeros_like(text) if uncond_text is None else uncond_text.to(text).expand_as(text)]),
        ref_2d=twice(ref_2d),
        ref_3d=twice(ref_3d),
        return_retrieval=return_retrieval,
    )
    conditional, unconditional = both.velocity.chunk(2)
    retrieval = both.retrieval.chunk(2)[0] if both.retrieval is not None else None
    return RestorerOutput(velocity=unconditional + guidance_scale * (conditional - unconditional),
                          retrieval=retrieval)


def negative_text(backbone: Backbone, guidance_scale: float) -> torch.Tensor | None:
    """The unconditional branch's text embedding (1, L, D) under ``backbone`` at ``guidance_scale``: the encoding of
    ``text_encoder.negative_prompt``, or None (the all-zero embedding) when no prompt is set or the sampling is
    unguided (scale 1: no unconditional branch is evaluated)."""
    if guidance_scale == 1.0 or backbone.cfg.text_encoder.negative_prompt is None:
        return None
    if backbone.text_encoder is None:
        raise ValueError("backbone.text_encoder.negative_prompt is set, so guided sampling encodes it, but the "
                         "backbone was built without its text encoder")
    return backbone.text_encoder.negative_embedding


def initial_noise(shape: torch.Size, generator: torch.Generator, device: torch.device | str) -> torch.Tensor:
    """eps ~ N(0, I) of a trajectory's first state, drawn on the CPU from ``generator`` so a seed gives the same
    states on any device."""
    return torch.randn(shape, generator=generator, dtype=torch.float32).to(device)


def first_state(schedule: NoiseSchedule, noise: torch.Tensor, temperature: float) -> torch.Tensor:
    """z_{t_M} of every reverse trajectory (deployment, the Stage-2 rollout, the trajectory diagnostics): the
    schedule's noise end for standard normal ``noise`` scaled by the sampling temperature (``SamplerConfig``)."""
    return schedule.prior(temperature * noise)


def partial_start(schedule: NoiseSchedule, grid: torch.Tensor, start: torch.Tensor, noise: torch.Tensor,
                  strength: float) -> tuple[torch.Tensor, torch.Tensor]:
    """SDEdit's start (Meng et al., ICLR 2022; diffusers' ``strength``): ``start`` (clean latents) noised to the
    grid's time ``strength`` of the way from its clean end, and the rest of the grid from there. Strength 1 is the
    whole grid from the noise end (``first_state``); lower keeps more of ``start``. As diffusers' video-to-video
    ``get_timesteps`` counts them, int(strength x M) of the M steps remain, here at least one."""
    steps = grid.numel() - 1
    kept = max(1, int(strength * steps))
    rest = grid[steps - kept:]
    return schedule.add_noise(start, noise, rest[0].expand(start.shape[0]).to(start.device)), rest


def solve(
    schedule: NoiseSchedule,
    grid: torch.Tensor,
    z: torch.Tensor,
    velocity: Callable[[int, torch.Tensor, torch.Tensor], torch.Tensor],
    progress: bool = False,
    keep_states: bool = False,
) -> list[torch.Tensor]:
    """The reverse-diffusion loop shared by deployment and the Stage-2 rollout (main paper Eqs. 1 and 4).

    From ``z`` at grid[0], for each step i: ``velocity(i, z_i, t_i)`` (t_i expanded to the batch) gives the
    direction, and the detached solver transition T_i moves to grid[i + 1]. Returns the visited states
    [z_{t_N}, ..., z_{t_0}] with ``keep_states``, else [z_{t_0}]. Deployment passes the guided velocity of one
    adapter; Stage 2 passes the student's guided velocity and supervises it at each state on the way, so the
    rollout visits exactly the states deployment visits for the same noise, grid, guidance and adapter.
    """
    batch, device = z.shape[0], z.device
    states = [z]
    pairs = list(zip(grid[:-1], grid[1:]))
    for i, (t, t_next) in enumerate(track(pairs, description="restoring", disable=not progress)):
        t_batch = t.expand(batch).to(device)
        v = velocity(i, z, t_batch).detach().float()
        z = schedule.step(z, v, t_batch, t_next.expand(batch).to(device)).detach()
        if keep_states:
            states.append(z)
    return states if keep_states else [z]


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
    temperature: float = 1.0,
    return_states: bool = False,
    progress: bool = False,
    grid: torch.Tensor | None = None,
    uncond_text: torch.Tensor | None = None,
    strength: float = 1.0,
) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
    """Run the M-step solver z_{t_M} -> z_{t_0} (``first_state`` at ``temperature``) conditioned on ``cond``
    latents (B, f, C, h, w); ``uncond_text`` is the guidance's unconditional branch (``guided_prediction``).
    ``strength`` < 1 starts from ``cond`` itself partly noised instead (``partial_start``: the last
    int(strength x M) steps), for a condition already near the clean end, such as the dense rendering R_d a
    pseudo-target restores.

    ``grid`` replaces the M-step deployment schedule (e.g. a Stage-2 training grid). bf16 autocast is used
    on CUDA. With ``return_states`` also returns the visited states [z_{t_M}, ..., z_{t_0}].
    """
    grid = schedule.timesteps(steps) if grid is None else grid
    autocast = (
        torch.autocast("cuda", dtype=torch.bfloat16)
        if cond.device.type == "cuda"
        else contextlib.nullcontext()
    )

    def velocity(_: int, z: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        with autocast:
            return guided_prediction(model, z, cond, t, text, ref_2d, ref_3d, guidance_scale,
                                     uncond_text=uncond_text).velocity

    noise = initial_noise(cond.shape, generator, cond.device)
    if strength < 1.0:
        z, grid = partial_start(schedule, grid, cond, temperature * noise, strength)
    else:
        z = first_state(schedule, noise, temperature)
    states = solve(schedule, grid, z, velocity, progress, keep_states=return_states)
    return (states[-1], states) if return_states else states[-1]


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
        strength: float = 1.0,
    ) -> torch.Tensor:
        """The same restoration from already encoded inputs (e.g. a prepared cache): clean latents. ``strength``:
        ``sample``'s (1: from noise, as deployment)."""
        cfg, device = self.backbone.cfg, self.device
        generator = torch.Generator().manual_seed(cfg.sampler.seed if seed is None else seed)
        guidance_scale = cfg.sampler.guidance_scale if guidance_scale is None else guidance_scale
        uncond_text = negative_text(self.backbone, guidance_scale)
        with using_adapter(self.backbone.transformer, self.adapter):
            return sample(
                self.backbone.transformer,
                self.backbone.schedule,
                cond.to(device),
                ref_2d.to(device),
                ref_3d.to(device),
                text.to(device),
                steps or cfg.schedule.deploy_steps,
                guidance_scale,
                generator,
                temperature=cfg.sampler.temperature,
                progress=progress,
                uncond_text=uncond_text,
                strength=strength,
            )
