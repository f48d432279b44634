"""What a preparation makes (paper Sec. 4.1 "Training Data"; supplement A.2): each scene loaded, split and
planned before anything is written, the view sets it fits and their snapshots, and every clip's student view count
K and trajectory by deployment's rule.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import torch

from tracegs.data.cache_keys import condition_key
from tracegs.data.captions import require_captioner
from tracegs.data.colmap import Scene, load_scene
from tracegs.data.config import PrepareConfig, PretrainPairs, SceneSourceConfig, Split
from tracegs.data.held_out import captured_clips
from tracegs.data.sources import is_procedural
from tracegs.data.splits import SceneSplit, require_sparse_in_dense, split_scene, view_set_key
from tracegs.data.synthetic import GT_PLY
from tracegs.splat.render import require_available
from tracegs.splat.trajectory import round_clips


class PrepareError(ValueError):
    """The preparation configuration or input data cannot be used."""


@dataclass
class ScenePlan:
    """A validated scene: its data, split and the fits it needs (view-set key -> snapshot iterations); for a
    captured scene's held-out split, its clips through captured cameras (``data.held_out``)."""

    scene: Scene
    split: SceneSplit
    fits: dict[str, list[int]]
    captured: list[dict] | None = None


def captures_held_out(source: SceneSourceConfig, cfg: PrepareConfig) -> bool:
    """Whether a scene's clips run through its captured cameras (the held-out split of a real dataset, whose only
    ground truth is the capture, or the pretraining split with ``pretrain_pairs=captured``) rather than along
    deployment's synthesised trajectory."""
    if cfg.split == Split.pretrain:
        return cfg.pretrain_pairs == PretrainPairs.captured
    return cfg.split == Split.test and not is_procedural(source)


def _view_counts(cfg: PrepareConfig) -> list[int | None]:
    return list(cfg.student_views) + list(cfg.dense_views)


def teacher_view_counts(cfg: PrepareConfig) -> list[int | None]:
    """View sets fitted to their final snapshot, so usable as a teacher condition ``d{V}``: the dense sets and,
    with ``student_final_fits``, the smallest sparse set (variant B's teacher for every student K, Table 3)."""
    return ([min(cfg.student_views)] if cfg.student_final_fits else []) + list(cfg.dense_views)


def plan_scene(source: SceneSourceConfig, cfg: PrepareConfig, name: str) -> ScenePlan:
    """Load and split a scene, and list the fits; raises before anything is written on bad input."""
    scene = load_scene(source, name)
    split = split_scene(scene, source, _view_counts(cfg))
    if cfg.split == Split.train:  # a held-out cache is scored as evaluation scores: on the benchmark's own sets
        require_sparse_in_dense(split, cfg.student_views, cfg.dense_views, scene.root, source.view_rule)
    finals = teacher_view_counts(cfg)
    fits: dict[str, list[int]] = {}
    for count in _view_counts(cfg):
        snapshots = set(fits.get(view_set_key(count), []))
        if count in finals:
            snapshots.add(cfg.fit.iterations)
        if count in cfg.student_views:
            snapshots |= set(cfg.student_snapshots)
        fits[view_set_key(count)] = sorted(snapshots)
    captured = (captured_clips(scene, split, list(cfg.student_views), cfg.frames_per_clip, cfg.held_out_repeat_frames)
                if captures_held_out(source, cfg) else None)
    if cfg.shared_trajectories and captured is None:
        smallest = min(cfg.student_views)
        for count in cfg.student_views:
            outside = sorted(set(split.views(smallest)) - set(split.views(count)))
            if outside:
                raise PrepareError(f"{scene.root}: views {outside[:5]} of the {smallest}-view set are not in the "
                                   f"{count}-view set, and data.prepare.shared_trajectories gives each trajectory "
                                   f"drawn on the {smallest} views to every K: use nested view sets "
                                   "(data.source.view_rule=nested) or set it to false")
    if cfg.pseudo_target == "gt" and captured is None and not (scene.root / GT_PLY).is_file():
        raise PrepareError(f"{scene.root / GT_PLY}: prepare.pseudo_target='gt' needs a ground-truth scene "
                           "(synthetic scenes, or a real dataset's held-out split); use 'restorer' or 'dense'")
    return ScenePlan(scene, split, fits, captured)


def require_inputs(cfg: PrepareConfig) -> None:
    """What preparation needs from this machine and disk: the rasterizer and the captioner.
    The settings' own rules are checked once, on the composed config (tracegs.config.validate)."""
    require_available(cfg.fit.backend, "data.prepare.fit.backend")
    require_captioner(cfg.captions, "data.prepare.captions")


def shard_scenes(names: list[str], shard_index: int, num_shards: int) -> list[str]:
    """The scenes of one shard: every ``num_shards``-th scene starting at ``shard_index``."""
    return names[shard_index::num_shards]


def scene_seed(seed: int, name: str) -> int:
    """A stable per-scene seed (Python's ``hash`` is salted per process, so use a digest)."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{name}".encode()).digest()[:4], "little")


def settings_digest(settings: object) -> str:
    """Short digest of the settings a work unit depends on: changed settings mean a different unit."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:10]


def clip_view_counts(cfg: PrepareConfig, scene: str) -> list[int]:
    """The student view count K of each clip of a scene: the clips divided evenly among ``student_views``, in
    an order seeded by the scene (which K gets one clip more differs between scenes); with
    ``shared_trajectories``, every K in turn for each trajectory."""
    if cfg.shared_trajectories:
        return [views for _ in range(trajectory_count(cfg)) for views in cfg.student_views]
    generator = torch.Generator().manual_seed(scene_seed(cfg.seed, f"{scene}/views"))
    order = [cfg.student_views[i] for i in torch.randperm(len(cfg.student_views), generator=generator).tolist()]
    return [order[c % len(order)] for c in range(cfg.clips_per_scene)]


def trajectory_count(cfg: PrepareConfig) -> int:
    """Distinct trajectories of a scene's clips, each restored into one pseudo-target: one per clip, or one per
    ``len(student_views)`` clips with ``shared_trajectories``."""
    return cfg.clips_per_scene // len(cfg.student_views) if cfg.shared_trajectories else cfg.clips_per_scene


def trajectory_seed(cfg: PrepareConfig, scene: str, views: int) -> int:
    """The seed of the generator that draws the trajectory rounds of a scene's K-view clips."""
    return scene_seed(cfg.seed, f"{scene}/K{views}")


def clip_cameras(plan: ScenePlan, cfg: PrepareConfig) -> list[dict]:
    """Clip trajectories by deployment's rule: a K-view clip is a clip of ``round_clips`` (with ``cfg.trajectory``,
    the deployment's trajectory config) on the K-view set, exactly as deployment from those K captured views
    makes it (every reference pair per round, as the paper scale deploys), rounds 0, 1, ... drawn from one
    generator per (scene, K) until that K has its share of the clips (``clip_view_counts``). A captured scene's
    held-out clips are its planned clips through captured cameras instead (every reference pair of every K).
    With ``shared_trajectories`` the trajectories are drawn on the smallest K's views and each serves every K
    (its clips consecutive). Each clip names its ``trajectory``: clips of one trajectory share a pseudo-target."""
    if plan.captured is not None:
        return plan.captured
    scene = plan.scene
    counts = clip_view_counts(cfg, scene.name)

    def trajectories(views: int, count: int) -> list[dict]:
        indices = plan.split.views(views)
        references = [scene.cameras[i] for i in indices]
        generator = torch.Generator().manual_seed(trajectory_seed(cfg, scene.name, views))
        drawn: list[dict] = []
        round_index = 0
        while len(drawn) < count:
            drawn += [{"refs": [indices[a], indices[b]], "cameras": cameras}
                      for (a, b), cameras in round_clips(references, round_index, cfg.trajectory, None, generator)]
            round_index += 1
        return drawn[:count]

    if cfg.shared_trajectories:
        drawn = trajectories(min(cfg.student_views), trajectory_count(cfg))
        return [{**drawn[c // len(cfg.student_views)], "views": views, "trajectory": c // len(cfg.student_views)}
                for c, views in enumerate(counts)]
    per_count = {views: iter(trajectories(views, counts.count(views))) for views in cfg.student_views}
    return [{**next(per_count[views]), "views": views, "trajectory": c} for c, views in enumerate(counts)]


def frames_stored(cfg: PrepareConfig) -> bool:
    """Whether shards keep uint8 frames: ``store_frames``, or by default only a held-out split's cache, whose
    clips evaluation scores in pixels (training reads latents only)."""
    return cfg.split != Split.train if cfg.store_frames is None else cfg.store_frames


def dense_condition(cfg: PrepareConfig) -> str | None:
    """Condition key of the densest configured view set (all views when listed), whose R_d feeds the
    pseudo-target generator; None when no dense set is prepared (a held-out cache that only scores restorers
    from R_s against ground truth)."""
    if not cfg.dense_views:
        return None
    return condition_key(None if None in cfg.dense_views else max(cfg.dense_views))


def clip_condition_keys(cfg: PrepareConfig, views: int) -> list[str]:
    """The conditions a K-view clip holds: its own K's student snapshots and every teacher condition."""
    return ([condition_key(views, snapshot) for snapshot in cfg.student_snapshots]
            + [condition_key(count) for count in teacher_view_counts(cfg)])
