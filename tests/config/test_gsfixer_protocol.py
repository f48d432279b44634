"""Where the paper says "same as GSFixer", the paper-scale configuration follows GSFixer's released code
(GVCLab/GSFixer, ``Reconstruction/``). Each test names the file and line of their code the value follows."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.config.validate import ConfigError, validate
from tracegs.splat.trajectory import clip_layout


def composed(config_name: str, overrides: list[str]):
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides)


@pytest.fixture(scope="module")
def paper():
    return composed("prepare", ["experiment=paper"])


# gsfixer/cogvideo/inference.py l. 323, the default of --negative_prompt.
GSFIXER_NEGATIVE_PROMPT = (
    "The video is not of a high quality, it has a low resolution. Watermark present in each frame. The background "
    "is solid. Strange body and strange trajectory. Distortion."
)


def test_opacity_reset_follows_gsfixers_mipnerf360_script(paper):
    """train_mipnerf360_sparse_view_recon_per_scene.py l. 49: ``--opacity_reset_interval 3100`` (the paper states
    no interval)."""
    assert paper.data.prepare.fit.densification.reset_every == 3100


def test_guidance_runs_against_gsfixers_negative_prompt(paper):
    """gsfixer/cogvideo/inference.py l. 320-325 (``--negative_prompt``), passed to the pipeline at l. 147 with
    guidance 6 (l. 305-309): the paper's unconditional branch is that prompt's T5 encoding."""
    assert paper.backbone.text_encoder.negative_prompt == GSFIXER_NEGATIVE_PROMPT
    assert paper.backbone.sampler.guidance_scale == 6.0
    assert paper.data.prepare.pseudo_target_guidance == 6.0


def test_the_embedded_scale_keeps_the_all_zero_unconditional_branch():
    assert composed("prepare", []).backbone.text_encoder.negative_prompt is None


def test_a_guided_rollout_is_refused_where_deployment_guides_against_a_negative_prompt():
    cfg = composed("train", ["experiment=paper", "stage=stage2", "stage.guidance_scale=6"])
    with pytest.raises(ConfigError, match="stage.guidance_scale"):
        validate(cfg)


@pytest.mark.parametrize("dataset, rule", [("mipnerf360", "linspace"), ("nerfbusters", "linspace"),
                                           ("dl3dv", "nested")])
def test_evaluation_datasets_pick_gsfixers_linspace_sparse_views(dataset, rule):
    """datasets/colmap_debug.py l. 416-422 (np.linspace over the every-8th split's training views) on the
    evaluation-only datasets; DL3DV trains too, whose clips need nested sets (paper Sec. 3)."""
    cfg = composed("prepare", ["experiment=paper", f"data={dataset}"])
    assert (cfg.data.source.view_rule, cfg.data.source.test_every) == (rule, 8)


def test_deployment_trajectory_follows_gsfixers_ellipse_and_clip_ends(paper):
    """gsfixer/extrapolation/outpaint/sparse.py l. 203 (``generate_ellipse_path(poses, 85, ...)``: 85 ellipse
    poses) and l. 286-297 (the captured reference images over the clip's rendered end frames); training clips
    follow the same trajectory config."""
    assert paper.deploy.trajectory.ellipse_frames == 85
    assert paper.deploy.trajectory.captured_ends is True
    assert paper.data.prepare.trajectory == paper.deploy.trajectory


def test_deployment_clips_are_gsfixers_windows_with_its_round_rule(paper):
    """gsfixer/extrapolation/outpaint/sparse.py l. 198-204 (round r: z_variation max(1.5 - 0.2 r, 0.5), pitch
    scale=r, i.e. 2r degrees, sample_utils.py l. 204-217), sample_utils.py l. 158-161 (semi-axes 1.2 x the 90th
    percentile every round) and l. 236-283 with base.py l. 13-34 (overlapping windows bridged to their nearest
    views, every window restored); rounds 0, 1, 2 are GSFixer's repair calls 0, 1, 2 (train.py l. 279-300)."""
    trajectory = paper.deploy.trajectory
    assert trajectory.clip_rule == "gsfixer_windows"
    assert list(trajectory.height_variations) == pytest.approx([max(1.5 - 0.2 * r, 0.5) for r in range(3)])
    assert list(trajectory.pitch_degrees) == [2.0 * r for r in range(3)]
    assert list(trajectory.ellipse_scales) == [1.2, 1.2, 1.2]
    assert len(paper.deploy.repair_iters) == 3  # one entry per repair round
    assert paper.deploy.max_clips_per_round is None
    assert clip_layout(trajectory.frames_per_clip) == (16, 17, 16)  # sparse.py l. 246-253: int(49 / 3) (+ 1)


def test_the_embedded_trajectory_keeps_its_own_values():
    trajectory = composed("prepare", []).deploy.trajectory
    assert (trajectory.ellipse_frames, trajectory.captured_ends) == (64, False)
    assert (trajectory.clip_rule, list(trajectory.pitch_degrees)) == ("reference_pairs", [0.0])
    assert (list(trajectory.ellipse_scales), list(trajectory.height_variations)) == ([1.0, 0.85, 0.7],
                                                                                     [0.05, 0.1, 0.15])


@pytest.mark.parametrize("overrides, field", [
    (["deploy.trajectory.clip_rule=gsfixer_windows", "deploy.max_clips_per_round=null",
      "deploy.trajectory.ellipse_frames=4"], "deploy.trajectory.ellipse_frames"),  # 9 frames: windows of 5
    (["deploy.trajectory.pitch_degrees=[2.0]"], "deploy.trajectory.pitch_degrees"),
])
def test_a_trajectory_gsfixers_rule_cannot_make_is_refused_naming_the_field(overrides, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        validate(composed("prepare", overrides))


# Each protocol field: (config key, GSFixer's release value, the corrected value, GSFixer's file and line).
PROTOCOL_FIELDS = [
    ("deploy.trajectory.ellipse_frame", "gsfixer_world", "focus",
     "gsfixer/extrapolation/outpaint/sample_utils.py l. 154-183; datasets/normalize.py l. 4-63"),
    ("deploy.kept_frames", "every", "between_ends", "gsfixer/extrapolation/outpaint/base.py l. 129-140"),
    ("data.prepare.fit.pseudo_ssim", "captured", "pseudo", "train.py l. 210-213"),
    ("data.prepare.fit.pseudo_densification", False, True, "train.py l. 198-202, 243"),
    ("data.prepare.fit.lr_opacities", 0.025, 0.05, "arguments/__init__.py l. 115"),
    ("data.prepare.fit.init_min_views", 1, 2, "datasets/colmap_debug.py l. 354-369"),
    ("backbone.reference_encoder.pixels", "uint8_wrap", "clean", "gsfixer/cogvideo/inference.py l. 106-119"),
    ("evaluation.ssim_convention", "gsfixer", "torchmetrics", "metrics.py l. 25-35, 74"),
    ("deploy.resolution", "dataset", "frame",
     "datasets/colmap_debug.py l. 160-170; arguments/__init__.py l. 64; base.py l. 63; train.py l. 204-208"),
    ("deploy.view_rule", "linspace", None, "datasets/colmap_debug.py l. 402-422"),
]


def value(cfg, key: str):
    node = cfg
    for part in key.split("."):
        node = node[part]
    return node


@pytest.mark.parametrize("key, release, corrected, where", PROTOCOL_FIELDS)
def test_the_paper_scale_deploys_as_gsfixer_released_it_and_corrected_names_each_fix(key, release, corrected, where):
    """Variant (A) is GSFixer: the paper scale's default protocol is the release's behaviour; ``corrected`` switches
    every field at once, and each stays overridable by name."""
    assert value(composed("prepare", ["experiment=paper"]), key) == release, where
    assert value(composed("prepare", ["experiment=paper", "deploy.protocol=corrected"]), key) == corrected, where
    override = "null" if corrected is None else corrected
    assert value(composed("prepare", ["experiment=paper", f"{key}={override}"]), key) == corrected


# The table's rows that are the release's under both protocols (nothing to correct): (key, value, file and line).
SHARED_FIELDS = [
    # train.py l. 246: ``size_threshold = 20 if iteration > opacity_reset_interval`` (the reference optimiser's).
    ("data.prepare.fit.densification.screen_prune_px", 20, "train.py l. 246"),
    # base.py l. 13-34 with sparse.py l. 236-283: 7 bridged windows a round.
    ("deploy.trajectory.clip_rule", "gsfixer_windows", "gsfixer/extrapolation/outpaint/base.py l. 13-34"),
]


@pytest.mark.parametrize("key, shared, where", SHARED_FIELDS)
def test_values_with_nothing_to_correct_follow_gsfixer_under_both_protocols(key, shared, where):
    for protocol in ("gsfixer_release", "corrected"):
        assert value(composed("prepare", ["experiment=paper", f"deploy.protocol={protocol}"]), key) == shared, where


def test_the_rehearsal_runs_gsfixers_release():
    assert composed("prepare", ["experiment=rehearsal"]).deploy.protocol == "gsfixer_release"


def test_the_embedded_scale_keeps_its_measured_values_under_its_own_protocol():
    """The embedded values are set field by field (``own``): kept frames and the pseudo term as corrected, no
    screen pruning (gsplat's default)."""
    cfg = composed("prepare", [])
    assert cfg.deploy.protocol == "own"
    assert (cfg.deploy.kept_frames, cfg.data.prepare.fit.pseudo_ssim) == ("between_ends", "pseudo")
    assert cfg.data.prepare.fit.pseudo_densification is True
    assert cfg.data.prepare.fit.densification.screen_prune_px is None
    assert (cfg.data.prepare.fit.lr_opacities, cfg.data.prepare.fit.init_min_views) == (0.05, 2)
    assert cfg.backbone.reference_encoder.pixels == "clean"
    assert cfg.evaluation.ssim_convention == "torchmetrics"
    assert (cfg.deploy.resolution, cfg.deploy.clip_size, cfg.deploy.view_rule) == ("frame", None, None)


def test_the_paper_scales_clips_reach_the_restorer_at_its_480x720():
    """train_mipnerf360_sparse_view_recon_per_scene.py l. 40-41: ``--diffusion_resize_width 720
    --diffusion_resize_height 480``, under both protocols."""
    for protocol in ("gsfixer_release", "corrected"):
        cfg = composed("prepare", ["experiment=paper", f"deploy.protocol={protocol}"])
        assert list(cfg.deploy.clip_size) == [480, 720]


def test_a_capture_of_ones_own_is_fitted_at_the_restorers_frames_under_every_protocol():
    cfg = composed("restore", ["experiment=paper"])
    assert (cfg.deploy.protocol, cfg.deploy.resolution) == ("gsfixer_release", "frame")


def test_every_protocol_field_is_a_row_of_the_cluster_docs_table():
    table = (Path(__file__).resolve().parents[2] / "docs" / "cluster.md").read_text()
    for key, release, corrected, where in PROTOCOL_FIELDS:
        (row,) = [line.lower() for line in table.splitlines() if f"| `{key.split('.')[-1]}` |" in line]
        for shown in (release, corrected):
            assert f"`{'null' if shown is None else shown}`".lower() in row, key
        assert where.split(" l. ")[0].split("/")[-1] in row, key
    for key, shared, where in SHARED_FIELDS:
        (row,) = [line.lower() for line in table.splitlines() if f"| `{key.split('.')[-1]}` |" in line]
        assert row.count(f"`{shared}`") >= 2 and where.split(" l. ")[0].split("/")[-1] in row, key
