"""A rendered clip made into what the cache stores (paper Sec. 4.1; supplement A.4): the pseudo-target,
the frozen encoders' codec latents, reference tokens and text embedding, the PSNR of each condition and the
contact sheet.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from PIL import Image
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.data import cache_keys
from tracegs.data.cache_keys import condition_key
from tracegs.data.captions import clip_caption
from tracegs.data.config import PrepareConfig
from tracegs.data.images import to_uint8
from tracegs.data.preparation.plan import (
    ScenePlan,
    dense_condition,
    frames_stored,
    scene_seed,
    teacher_view_counts,
)
from tracegs.data.preparation.shards import EncodedClip, write_clip
from tracegs.io import atomic_write
from tracegs.restorer.build import Backbone
from tracegs.splat.cameras import Camera


def backbone_device(backbone: Backbone) -> torch.device:
    """The accelerator the backbone was built on."""
    return next(backbone.transformer.parameters()).device


def encode_frames(backbone: Backbone, frames: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Codec latents of named clips (each (F, 3, H, W) in [0, 1]), encoded as one batch on the backbone's device."""
    if not frames:
        return {}
    latents = backbone.codec.encode(torch.stack([clip.cpu() for clip in frames.values()]).to(backbone_device(backbone)))
    return dict(zip(frames, latents))


def stored_tokens(latents: dict[str, torch.Tensor], references: tuple[torch.Tensor, torch.Tensor],
                  text: torch.Tensor, dtype: torch.dtype
                  ) -> tuple[dict[str, torch.Tensor], tuple[torch.Tensor, torch.Tensor], torch.Tensor, torch.Tensor]:
    """What a shard and its scene files store, in the cache's dtype: the codec latents of every condition and the
    target, the 2D tokens of each reference view, the pair's 3D tokens and the text embedding."""
    ref_2d, ref_3d = references
    # The encoder returns both views' 2D tokens concatenated, first view first, each computed from its view
    # alone (DINOv2 per view), so each half is that view's tokens in any pair.
    first, second = ref_2d[0].to("cpu", dtype).chunk(2)
    return ({cache_keys.latent(k): latent.to("cpu", dtype) for k, latent in latents.items()},
            (first.clone(), second.clone()), ref_3d[0].to("cpu", dtype), text[0].to("cpu", dtype))


def restorer_pipeline(backbone: Backbone):
    """The frozen pseudo-target generator (supplement A.4): the pretrained restorer itself, no adapter.

    GSFixer releases one transformer folder, so theta with phi_pre is that folder: the generator is the frozen
    base, which is also variant (A) and Stage 1's starting point (B = 0 at attachment, Eq. supp-lora).
    """
    from tracegs.restorer.sampler import RestorationPipeline

    return RestorationPipeline(backbone)


@dataclass
class SharedTrajectory:
    """What the clips of one trajectory have in common under ``shared_trajectories`` (paper: 25 trajectories x 3 K
    per scene): its pseudo-target and the codec latents of its teacher conditions and target. Its first clip makes
    them, the trajectory's other clips (consecutive) reuse them, so R_d is encoded and restored once per
    trajectory, not once per clip."""

    trajectory: int | None = None
    target: torch.Tensor | None = None
    latents: dict[str, torch.Tensor] = field(default_factory=dict)


def pseudo_target(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
                  ground_truth: torch.Tensor | None, dense_latent: torch.Tensor | None,
                  references: tuple[torch.Tensor, torch.Tensor], caption: str, cfg: PrepareConfig,
                  backbone: Backbone, pipeline) -> torch.Tensor:
    """The clip's target frames: ground truth, R_d itself, or R_d restored by the frozen restorer from its codec
    latent ``dense_latent`` (supplement A.4). A restoration shared by a trajectory's clips is captioned from R_d
    and seeded by the trajectory, which its clips have in common, so a resumed preparation makes the same one."""
    if cfg.pseudo_target == "gt":
        return ground_truth
    dense = conditions[dense_condition(cfg)]
    if cfg.pseudo_target == "dense":
        return dense
    if cfg.shared_trajectories:
        seed = scene_seed(cfg.seed, f"{plan.scene.name}/trajectory{clip['trajectory']}")
        caption = clip_caption(cfg.captions, dense[0], plan.scene.caption)
    else:
        seed = scene_seed(cfg.seed, f"{plan.scene.name}/{index}")
    latents = pipeline.restore_latents(dense_latent[None], *references, backbone.text_encoder.encode([caption]),
                                       seed=seed, guidance_scale=cfg.pseudo_target_guidance,
                                       strength=cfg.pseudo_target_strength)
    return backbone.codec.decode(latents)[0].clamp(0, 1).cpu()


def clip_latents(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
                 ground_truth: torch.Tensor | None, references: tuple[torch.Tensor, torch.Tensor], caption: str,
                 cfg: PrepareConfig, backbone: Backbone, pipeline, shared: SharedTrajectory
                 ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The clip's pseudo-target and the codec latents of its conditions and target (key ``target``).

    Without shared trajectories a clip's conditions and target are one batch (a restored target: the conditions
    first, R_d's latent restored, then the target). With them, ``shared`` holds the trajectory's teacher
    latents, pseudo-target and target latent (made as one batch of teacher conditions, then the target, by
    whichever of its clips comes first, also on a resumed run), and each clip encodes its own student conditions
    only."""
    dense = dense_condition(cfg)
    # A held-out clip through captured photographs (tracegs.data.held_out) belongs to no drawn trajectory.
    if not cfg.shared_trajectories or "trajectory" not in clip:
        if cfg.pseudo_target != "restorer":
            target = pseudo_target(plan, clip, index, conditions, ground_truth, None, references, caption, cfg,
                                   backbone, pipeline)
            return target, encode_frames(backbone, {**conditions, cache_keys.TARGET: target})
        latents = encode_frames(backbone, conditions)
        target = pseudo_target(plan, clip, index, conditions, ground_truth, latents[dense], references, caption, cfg,
                               backbone, pipeline)
        return target, latents | encode_frames(backbone, {cache_keys.TARGET: target})
    teacher = {condition_key(count) for count in teacher_view_counts(cfg)}
    if shared.trajectory != clip["trajectory"]:
        latents = encode_frames(backbone, {k: frames for k, frames in conditions.items() if k in teacher})
        target = pseudo_target(plan, clip, index, conditions, ground_truth, latents.get(dense), references, caption,
                               cfg, backbone, pipeline)
        latents |= encode_frames(backbone, {cache_keys.TARGET: target})
        shared.trajectory, shared.target, shared.latents = clip["trajectory"], target, latents
    own = encode_frames(backbone, {k: frames for k, frames in conditions.items() if k not in teacher})
    return shared.target, {k: own[k] if k in own else shared.latents[k] for k in [*conditions, cache_keys.TARGET]}


def save_clip(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
              ground_truth: torch.Tensor | None, cfg: PrepareConfig, backbone: Backbone, pipeline,
              scene_dir: Path, settings: str, shared: SharedTrajectory, sheet: Path | None = None) -> None:
    """Pseudo-target and codec latents (``clip_latents``; ``shared``: the trajectory's, reused by its clips), the
    frozen encoders' tokens and files of one rendered clip (each condition's PSNR vs GT in its metadata); with
    ``sheet``, the contact sheet of its frames too (before its shard, so a finished shard has its sheet)."""
    cameras: list[Camera] = clip["cameras"]
    views = clip["views"]
    a, b = clip["refs"]
    ref_images = torch.stack([plan.scene.load_image(a), plan.scene.load_image(b)])
    # One caption per clip, from the first frame of its earliest-snapshot R_s (the paper does not say which of
    # the clip's R_s; the most degraded one is what deployment from K views renders first).
    student = condition_key(views, min(cfg.student_snapshots))
    caption = clip_caption(cfg.captions, conditions[student][0], plan.scene.caption)
    with torch.no_grad():
        references = backbone.reference_encoder(ref_images[None].to(backbone_device(backbone)))
        target, latents = clip_latents(plan, clip, index, conditions, ground_truth, references, caption, cfg,
                                       backbone, pipeline, shared)
        tensors, ref_2d, ref_3d, text = stored_tokens(latents, references, backbone.text_encoder.encode([caption]),
                                                      getattr(torch, cfg.latent_dtype))
    pixels = {**conditions, cache_keys.TARGET: target, cache_keys.REFERENCE: ref_images}
    if ground_truth is not None:
        pixels[cache_keys.GROUND_TRUTH] = ground_truth
    if sheet is not None:
        contact_sheet(pixels, sheet, [k for k in (student, dense_condition(cfg)) if k is not None])
    if frames_stored(cfg):
        tensors.update({cache_keys.frames(key): to_uint8(frames) for key, frames in pixels.items()})
    tensors[cache_keys.POSES] = torch.stack([c.world_to_camera for c in cameras]).float()
    tensors[cache_keys.INTRINSICS] = torch.stack([c.K for c in cameras]).float()
    psnr = {}
    if ground_truth is not None:
        psnr = {key: psnr_on_path(frames, ground_truth) for key, frames in conditions.items()}
    metadata = {"scene": plan.scene.name, "clip": str(index), "pseudo_target": cfg.pseudo_target,
                "psnr_vs_gt": json.dumps(psnr)}
    if "images" in clip:
        metadata |= {cache_keys.META_CAPTURED_IMAGES: json.dumps(clip["images"]),
                     cache_keys.META_CAPTURE_ORDER: clip["capture_order"]}
    write_clip(scene_dir, index, EncodedClip(tensors, views, (a, b), caption, ref_2d, ref_3d, text), metadata,
               settings)


def psnr_on_path(frames: torch.Tensor, reference: torch.Tensor) -> float:
    """PSNR on the trajectory frames, excluding the two reference frames at the clip ends."""
    return float(peak_signal_noise_ratio(frames[1:-1], reference[1:-1], data_range=1.0))


def contact_sheet(pixels: dict[str, torch.Tensor], out: Path, columns: list[str]) -> None:
    """PNG with one row per frame of a clip: the listed conditions, then the target (and ground truth when
    known), from the clip's frames in [0, 1] as rendered (so a cache without stored frames has its sheet)."""
    keys = [*columns, cache_keys.TARGET] + ([cache_keys.GROUND_TRUTH] if cache_keys.GROUND_TRUTH in pixels else [])
    frames = [to_uint8(pixels[k]) for k in keys]
    rows = torch.cat([torch.cat([c[i] for c in frames], dim=2) for i in range(frames[0].shape[0])], dim=1)
    with atomic_write(out) as tmp:
        Image.fromarray(rows.permute(1, 2, 0).numpy()).save(tmp, format="PNG")
