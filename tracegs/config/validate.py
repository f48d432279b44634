"""Cross-field rules that the typed schema cannot express.

Types and key names are checked by OmegaConf when Hydra composes the config, each numeric value against the
range its field declares (tracegs.ranges) first here; the other rules here relate several fields (a teacher
sees more views than every student set or is one, N <= M, 8k+1 clips, ...).
Every error names the offending field so a sweep with a bad point fails with a one-line message.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigKeyError

from tracegs.data.colmap import require_training_source
from tracegs.data.config import clip_target, overlapping_seeds
from tracegs.data.sources import is_procedural
from tracegs.data.synthetic import TEXTURES, benchmark_scene_names
from tracegs.deploy.config import METHODS
from tracegs.errors import ConfigError, require_plain_name
from tracegs.eval.metrics import require_lpips
from tracegs.location import CONF_DIR
from tracegs.ranges import ranges
from tracegs.stages import Product

__all__ = ["ConfigError", "validate", "validate_names", "validate_ranges"]


def _require(condition: bool, field: str, message: str) -> None:
    if not condition:
        raise ConfigError(field, message)


def _is_8k_plus_1(frames: int) -> bool:
    return frames >= 9 and (frames - 1) % 8 == 0


def _views_label(views: int | None) -> str:
    return "all" if views is None else str(views)


def _check_increasing(values: Iterable[int], field: str) -> list[int]:
    values = list(values)
    _require(all(a < b for a, b in zip(values, values[1:])), field, f"must be strictly increasing, got {values}")
    return values


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` naming the first field whose value is inconsistent with the others."""
    _validate_known_keys(cfg)
    validate_ranges(cfg)
    validate_names(cfg)
    _validate_data(cfg)
    _validate_training(cfg)
    _validate_backbone(cfg)
    _validate_deployment(cfg)
    _validate_evaluation(cfg)


def _validate_known_keys(cfg: DictConfig) -> None:
    """Every key must be a field of the schema. Hydra's ``+key=value`` adds keys past struct mode (it is
    even Hydra's hint for a misspelt override), so the composed tree is merged into the schema once more, as
    plain containers: a node keeps its added keys when merged as a typed node."""
    from tracegs.config.schema import TraceGSConfig

    tree = OmegaConf.to_container(cfg)
    tree.pop("hydra", None)  # Hydra's own node, present when composed with return_hydra_config
    try:
        OmegaConf.merge(OmegaConf.structured(TraceGSConfig), tree)
    except ConfigKeyError as error:
        field = error.full_key or str(error.key)
        raise ConfigError(field, "is not a field of the schema (misspelt, or added with '+'); "
                                 "see --cfg job for the valid keys") from error


def validate_ranges(cfg: DictConfig) -> None:
    """Every numeric value in the range its field declares. The values given first, then those interpolated from
    others, so the field named is the one the user typed (``seed``, not a part seed derived from it; tracegs-restore's
    ``capture.views``, not the ``evaluation.views`` made of it)."""
    from tracegs.config.schema import TraceGSConfig

    declared_ranges = ranges(TraceGSConfig)
    raw = OmegaConf.to_container(cfg, resolve=False)

    def interpolated(field: str) -> bool:
        node = raw
        for key in field.split("."):
            node = node[key]
        return "${" in str(node)

    for field in sorted(declared_ranges, key=interpolated):
        declared = declared_ranges[field]
        value = OmegaConf.select(cfg, field, throw_on_missing=True)
        if isinstance(value, ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
        problem = declared.problem(value)
        if problem is not None:
            raise ConfigError(field, problem)


# Config values that become one folder name under a configured root (lists: every item).
NAME_FIELDS = ("experiment.name", "ablation.name", "data.name", "training_data", "data.source.scenes",
               "data.datamodule.val_scenes", "evaluation.scenes", "report.datasets", "report.main_datasets",
               "stage.deployment_eval.scenes")


def validate_names(cfg: DictConfig) -> None:
    """Every :data:`NAME_FIELDS` value is a plain name (checked before Hydra makes the run folder of them too)."""
    for field in NAME_FIELDS:
        value = OmegaConf.select(cfg, field)
        for item in ([] if value is None else [value] if isinstance(value, str) else value):
            require_plain_name(str(item), field)


def _validate_data(cfg: DictConfig) -> None:
    synthetic, prepare, datamodule = cfg.data.synthetic, cfg.data.prepare, cfg.data.datamodule
    overlap = overlapping_seeds(synthetic)
    _require(not overlap, "data.synthetic.test_seeds",
             f"train_seeds, val_seeds, test_seeds and pretrain_seeds must be disjoint, seeds in more than one: "
             f"{overlap}")
    unknown = [name for name in synthetic.get("pretrain_textures") or [] if name not in TEXTURES]
    _require(not unknown, "data.synthetic.pretrain_textures",
             f"{unknown} are not among the photographs a scene can be textured with: {sorted(TEXTURES)}")
    _require(
        _is_8k_plus_1(prepare.frames_per_clip),
        "data.prepare.frames_per_clip",
        f"clips must have 8k+1 frames (9, 17, 25, 49: the CogVideoX VAE contract), got {prepare.frames_per_clip}",
    )
    _require(
        prepare.split != "val" or is_procedural(cfg.data.source),
        "data.prepare.split",
        "'val': only the synthetic benchmark has a validation split; a real dataset prepares 'train' or 'test'",
    )
    _validate_training_data(cfg)
    fit = prepare.fit  # the one 3DGS optimiser config (splat group), used by preparation and deployment
    snapshots = _check_increasing(fit.snapshot_iters, "data.prepare.fit.snapshot_iters")
    _require(
        snapshots and snapshots[-1] <= fit.iterations,
        "data.prepare.fit.snapshot_iters",
        f"snapshots {snapshots} must lie inside the fit budget of {fit.iterations} iterations",
    )
    missing = sorted(set(prepare.student_snapshots) - set(snapshots))
    _require(not missing, "data.prepare.student_snapshots",
             f"{missing} are not among data.prepare.fit.snapshot_iters {snapshots}")
    # A student condition R_s is an intermediate snapshot: the final one is the dense fits' (and R_d's).
    final = [s for s in prepare.student_snapshots if not 0 < s < fit.iterations]
    _require(not final, "data.prepare.student_snapshots",
             f"{final} must lie in (0, data.prepare.fit.iterations={fit.iterations})")
    _require(0 <= prepare.shard_index < prepare.num_shards, "data.prepare.shard_index",
             f"{prepare.shard_index} must lie in [0, data.prepare.num_shards={prepare.num_shards})")
    _require(not prepare.shared_trajectories or prepare.clips_per_scene % len(prepare.student_views) == 0,
             "data.prepare.clips_per_scene",
             f"{prepare.clips_per_scene} is not a multiple of the {len(prepare.student_views)} student view counts, "
             "which data.prepare.shared_trajectories gives every trajectory to")
    student_sets = _check_increasing(prepare.student_views, "data.prepare.student_views")
    target = clip_target(prepare.split, prepare.pseudo_target, is_procedural(cfg.data.source))
    _require(bool(prepare.dense_views) or target == "gt", "data.prepare.dense_views",
             f"is empty, but data.prepare.pseudo_target={prepare.pseudo_target!r} is made from a dense rendering R_d")
    dense_counts = [v for v in prepare.dense_views if v is not None]
    _check_increasing(dense_counts, "data.prepare.dense_views")
    _require(
        not dense_counts or dense_counts[0] > student_sets[-1],
        "data.prepare.dense_views",
        f"dense view sets {dense_counts} must be larger than every student set {student_sets} (V_s in V_d)",
    )
    if prepare.split == "train":  # the datamodule reads the train split's cache, whatever split a run prepares
        # ... or, for A under the paper's data protocol, its pretraining split's (data.prepare.pretrain_views).
        pretrained = cfg.stage.name == Product.baseline and cfg.experiment.baseline_split == "pretrain"
        field = "data.prepare.pretrain_views" if pretrained and prepare.pretrain_views else "data.prepare.student_views"
        unknown = sorted(set(datamodule.student_views) - set(OmegaConf.select(cfg, field)))
        _require(not unknown, "data.datamodule.student_views", f"{unknown} are not prepared ({field})")
        unknown = sorted(set(datamodule.student_snapshots) - set(prepare.student_snapshots))
        _require(not unknown, "data.datamodule.student_snapshots",
                 f"{unknown} are not prepared (data.prepare.student_snapshots)")


def _validate_training_data(cfg: DictConfig) -> None:
    """``training_data`` and the datasets of Tables 1-3 are ``data`` options; training runs on the training data,
    whose scenes are never benchmark scenes."""
    options = sorted(path.stem for path in (Path(CONF_DIR) / "data").glob("*.yaml"))
    for field, names in (("training_data", [cfg.training_data]), ("report.datasets", cfg.report.datasets),
                         ("report.main_datasets", cfg.report.main_datasets)):
        for name in names:
            _require(name in options, field, f"{name!r} is not a data option (conf/data/<name>.yaml); choose from "
                                             f"{options}")
    if cfg.task == "train":  # the trained products are looked up on training_data (tracegs.pipeline.upstream)
        _require(cfg.data.name == cfg.training_data, "training_data",
                 f"{cfg.training_data!r}, but this run trains on data={cfg.data.name}: the restorers train on "
                 f"the training data; set training_data={cfg.data.name} here and for the commands that use them")
    # Never benchmark scenes: preparing training clips reads the scene lists (the test split is the benchmark's
    # held-out clips); training, which reads the cache, refuses from the config alone a dataset with no training
    # list (a benchmark's every scene).
    source = cfg.data.source
    unlisted = source.scenes is None and source.train_list is None
    preparing_training = cfg.task == "prepare" and cfg.data.prepare.split == "train"
    if not is_procedural(source) and (preparing_training or (cfg.task == "train" and unlisted)):
        require_training_source(OmegaConf.to_object(source))


def _validate_training(cfg: DictConfig) -> None:
    teacher, prepare = cfg.teacher, cfg.data.prepare
    student_max = max(cfg.data.datamodule.student_views)
    # Of the sparse sets only the smallest is fitted to its final snapshot (variant B's teacher,
    # tracegs.data.preparation.plan).
    available = {*([min(prepare.student_views)] if prepare.student_final_fits else []), *prepare.dense_views}
    fix = ("set data.prepare.student_final_fits=true" if teacher.views == min(prepare.student_views)
           else "a sparse teacher is the smallest student set" if teacher.views in prepare.student_views
           else "add it to data.prepare.dense_views")
    # Stage 2 reads the train split's cache; a held-out cache may leave the teacher out (the demo's does).
    _require(
        prepare.split != "train" or teacher.views in available,
        "teacher.views",
        f"{_views_label(teacher.views)} views are not prepared to their final snapshot; prepared sets: "
        f"{sorted(_views_label(v) for v in available)} ({fix})",
    )
    # Privileged or not is the view count itself: above every student set (C, D, E, F) or a student set
    # (variant B). A count in between would be privileged for some student K and not for others.
    _require(
        teacher.views is None or teacher.views > student_max or teacher.views in cfg.data.datamodule.student_views,
        "teacher.views",
        f"{_views_label(teacher.views)} teacher views are neither above every student set (up to {student_max}, "
        "privileged) nor a student set (variant B)",
    )
    deploy_steps = cfg.backbone.schedule.deploy_steps
    _require(
        1 <= cfg.stage.rollout_steps <= deploy_steps,
        "stage.rollout_steps",
        f"Stage-2 rollout N={cfg.stage.rollout_steps} must be in [1, M] with M=backbone.schedule.deploy_steps="
        f"{deploy_steps} (the grid is resampled from the deployment schedule)",
    )
    # Training reads cached text embeddings and never loads the text encoder, so a guided rollout has no encoding
    # of a negative prompt: its unconditional branch would differ from deployment's.
    _require(
        cfg.stage.guidance_scale == 1.0 or cfg.backbone.text_encoder.negative_prompt is None,
        "stage.guidance_scale",
        f"{cfg.stage.guidance_scale} guides the Stage-2 rollout, but training has no encoding of "
        "backbone.text_encoder.negative_prompt (deployment's unconditional branch); use 1 or negative_prompt=null",
    )
    _validate_deployment_eval(cfg)


def _validate_deployment_eval(cfg: DictConfig) -> None:
    """Training deploys on validation scenes only: on the synthetic benchmark, its val split (never a scene it
    trains on or is tested on)."""
    scenes = list(cfg.stage.deployment_eval.scenes)
    if scenes and is_procedural(cfg.data.source):
        validation = benchmark_scene_names(OmegaConf.to_object(cfg.data.synthetic), "val")
        others = sorted(set(scenes) - set(validation))
        _require(not others, "stage.deployment_eval.scenes",
                 f"{others[:5]} are not validation scenes of the synthetic benchmark ({validation})")


def _validate_backbone(cfg: DictConfig) -> None:
    backbone = cfg.backbone
    _require(
        backbone.schedule.deploy_time_power == 0 or backbone.schedule.kind == "rectified_flow",
        "backbone.schedule.deploy_time_power",
        f"is for schedule.kind=rectified_flow only (the DDIM grid is CogVideoX's own), got "
        f"{backbone.schedule.deploy_time_power} with '{backbone.schedule.kind}'",
    )
    _require(
        backbone.transformer.prediction == "velocity" or backbone.schedule.kind == "rectified_flow",
        "backbone.transformer.prediction",
        f"'{backbone.transformer.prediction}' converts x0 to a rectified-flow velocity; schedule.kind is "
        f"'{backbone.schedule.kind}' (use prediction=velocity)",
    )
    transformer, schedule = backbone.transformer, backbone.schedule
    _require(schedule.noise_scale == 1 or schedule.kind == "rectified_flow", "backbone.schedule.noise_scale",
             f"is for schedule.kind=rectified_flow only, got {schedule.noise_scale} with '{schedule.kind}'")
    _require(transformer.prediction != "preconditioned" or transformer.noise_scale == schedule.noise_scale,
             "backbone.transformer.noise_scale",
             f"must be the schedule's noise end (backbone.schedule.noise_scale = {schedule.noise_scale}): the "
             f"preconditioning is derived from it, got {transformer.noise_scale}")
    _require(schedule.train_loss_weighting == "uniform" or transformer.prediction == "preconditioned",
             "backbone.schedule.train_loss_weighting",
             f"'edm' needs backbone.transformer.prediction=preconditioned, got '{transformer.prediction}'")
    logit_normal = schedule.train_time_logit_normal
    _require(logit_normal is None or (len(logit_normal) == 2 and logit_normal[1] > 0),
             "backbone.schedule.train_time_logit_normal", f"must be [mean, std > 0] or null, got {logit_normal}")
    # The codec's spatial factor times the patch size must tile the rendered frames exactly (the CogVideoX
    # VAE compresses 8x spatially, supplement A.1; the embedded codec by its block size).
    factor = (8 if backbone.codec.kind == "cogvideox" else backbone.codec.block_size) * backbone.transformer.patch_size
    height, width = cfg.data.synthetic.height, cfg.data.synthetic.width
    if not is_procedural(cfg.data.source) and cfg.data.source.height is not None:
        height, width = cfg.data.source.height, cfg.data.source.width
    # The data groups take their frame size from the experiment, so a backbone chosen without its scale
    # fails here: say which experiment sizes frames for it.
    scale_hint = ", or use experiment=paper (480x720 frames)" if backbone.codec.kind == "cogvideox" else ""
    _require(
        height % factor == 0 and width % factor == 0,
        "backbone.transformer.patch_size",
        f"frames of {height}x{width} are not divisible by codec factor x patch size = {factor}; set "
        f"experiment.frame_height/frame_width to multiples of {factor}{scale_hint}",
    )


def _validate_deployment(cfg: DictConfig) -> None:
    # The refinement schedule's own rules live with it (RefinementConfig.validate, also used by library
    # callers), naming its fields relative to itself.
    try:
        OmegaConf.to_object(cfg.deploy).validate()
    except ConfigError as error:
        raise error.under("deploy") from error
    clip_frames = cfg.deploy.trajectory.frames_per_clip
    _require(
        clip_frames == cfg.data.prepare.frames_per_clip,
        "deploy.trajectory.frames_per_clip",
        f"deployment clips ({clip_frames} frames) must match the training clips "
        f"(data.prepare.frames_per_clip={cfg.data.prepare.frames_per_clip})",
    )


# Commands that score images (and so compute LPIPS when the experiment requires it).
SCORING_TASKS = ("evaluate", "restore", "demo", "replicate")


def _validate_evaluation(cfg: DictConfig) -> None:
    if cfg.task in SCORING_TASKS:  # before any work: the paper's tables are not made without LPIPS
        require_lpips(cfg.evaluation.lpips, cfg.evaluation.require_lpips, cfg.evaluation.lpips_weights)
    unknown = [m for m in cfg.evaluation.methods if m not in METHODS]
    _require(not unknown, "evaluation.methods", f"unknown methods {unknown}; choose from {list(METHODS)}")
