"""The Hydra config tree: every file composes, the ablation grid matches Table 3, bad input fails."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from tracegs.cli.app import CONF_DIR
from tracegs.config.validate import ConfigError, validate
from tracegs.pipeline.runner import override
from tracegs.pipeline.steps import SWEEP_TEACHERS

CONF = Path(CONF_DIR)
REPO = Path(__file__).resolve().parents[2]
SHARED = "command"  # conf/command.yaml: the defaults list and Hydra settings every entry point includes
PRIMARY = sorted(p.stem for p in CONF.glob("*.yaml") if p.stem != SHARED)

# Table 3 of the paper: variant -> (teacher views, privileged, on-policy, lambda_ret, trains Stage 2).
ABLATION_GRID = {
    "A": (None, True, True, 0.15, False),
    "B": (3, False, True, 0.15, True),
    "C": (12, True, True, 0.15, True),
    "D": (18, True, True, 0.15, True),
    "E": (None, True, False, 0.15, True),
    "F-": (None, True, True, 0.0, True),
    "F": (None, True, True, 0.15, True),
}

# Options that cannot run at the other scale: they must fail validation saying which experiment they need.
NEEDS_EXPERIMENT = {
    ("embedded", "backbone", "cogvideox5b"): "experiment=paper",
    # (The embedded scale prepares the teacher of the variant a command runs for: every ablation and teacher
    # option composes there too.)
}
# A benchmark-only dataset trained on (its every scene a test scene) is refused from the config alone.
NEEDS_EXPERIMENT.update({(scale, "data", option): "benchmark scenes included"
                         for scale in ("embedded", "paper") for option in ("mipnerf360", "nerfbusters")})


pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


def group_options() -> list[tuple[str, str]]:
    """Every non-primary config file as (group, option), found by walking conf/ so new files are covered.
    A group's ``base/`` folder holds what its options share (``conf/data/base/``): no option of its own."""
    options = []
    for path in sorted(CONF.rglob("*.yaml")):
        rel = path.relative_to(CONF)
        if len(rel.parts) > 1 and "base" not in rel.parts[:-1]:
            options.append(("/".join(rel.parts[:-1]), rel.stem))
    return options


def test_walk_finds_every_group():
    groups = {g for g, _ in group_options()}
    expected = {"backbone", "data", "splat", "stage", "teacher", "policy", "loss", "trainer", "experiment",
                "ablation", "debug", "deploy", "evaluation", "hydra/launcher"}
    assert expected <= groups
    assert set(PRIMARY) == {"prepare", "train", "deploy", "evaluate", "report", "demo", "restore", "replicate"}


@pytest.mark.parametrize("name", PRIMARY)
def test_entry_points_share_one_defaults_list(name):
    """Each entry point's defaults list is the shared file and itself: a group default lives in one place.
    An entry point may only choose another option of a shared group (``override``), never add a default."""
    defaults = list(OmegaConf.load(CONF / f"{name}.yaml").defaults)
    assert defaults[0] == SHARED and defaults[-1] == "_self_"
    assert all(next(iter(entry)).startswith("override ") for entry in defaults[1:-1])


def test_task_and_modes_are_checked_at_composition():
    with pytest.raises(ConfigCompositionException) as error:
        compose(config_name="report", overrides=["report.kind=tables"])
    assert "report.kind" in str(error.value.__cause__ or error.value)
    assert compose(config_name="report", overrides=["report.kind=ablation"]).job_name == "report-ablation"


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose_and_validate(name):
    cfg = compose(config_name=name, return_hydra_config=True)
    assert cfg.task == name
    validate(cfg)
    # Every value resolves (no dangling interpolation); Hydra's own node is checked by Hydra.
    resolved = OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)
    assert resolved["run_dir"]


@pytest.mark.parametrize("scale", ["embedded", "paper"])
@pytest.mark.parametrize(("group", "option"), group_options())
def test_every_group_option_composes_alone_at_either_scale(group, option, scale):
    """Each option chosen on its own: dataset sizes come from the experiment, so every data / splat /
    deploy option validates at both scales; what cannot (a backbone needing other frame sizes) says
    which experiment it needs."""
    if group == "hydra/launcher":
        cfg = compose(config_name="train", overrides=[f"{group}={option}"], return_hydra_config=True)
        launcher = cfg.hydra.launcher
        if option == "slurm":
            assert launcher.nodes == cfg.trainer.num_nodes
            assert str(launcher.tasks_per_node) == str(cfg.trainer.devices)  # training: a rank per device
            assert launcher.max_num_timeout == 0  # Lightning, not submitit, owns requeueing
        return
    trained_on = [f"training_data={option}"] if group == "data" else []  # training runs on the training data
    cfg = compose(config_name="train", overrides=[f"experiment={scale}", f"{group}={option}", *trained_on])
    OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)
    needed = NEEDS_EXPERIMENT.get((scale, group, option))
    if needed is None:
        validate(cfg)
        return
    with pytest.raises(ConfigError) as error:
        validate(cfg)
    assert needed in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("data", ["synthetic", "dl3dv", "mipnerf360", "nerfbusters"])
def test_dataset_options_are_sized_by_the_experiment(data):
    for scale, size, frames in (("embedded", (48, 72), 9), ("paper", (480, 720), 49)):
        cfg = compose(config_name="train", overrides=[f"experiment={scale}", f"data={data}"])
        sized = cfg.data.synthetic if data == "synthetic" else cfg.data.source
        assert (sized.height, sized.width) == size
        assert cfg.data.prepare.frames_per_clip == frames == cfg.deploy.trajectory.frames_per_clip
        assert list(cfg.data.prepare.student_snapshots) == list(cfg.data.prepare.fit.snapshot_iters)[:2]




@pytest.mark.parametrize("variant", sorted(ABLATION_GRID))
def test_ablation_variants_match_design(variant):
    views, privileged, on_policy, lambda_ret, trains = ABLATION_GRID[variant]
    cfg = compose(config_name="train", overrides=[f"ablation={variant}", *(override(k, v) for k, v in SWEEP_TEACHERS.items())])
    validate(cfg)
    assert cfg.ablation.name == variant
    assert cfg.teacher.views == views
    # privileged = the teacher sees more views than every student set (variant B's 3 views do not)
    assert (cfg.teacher.views is None or cfg.teacher.views > max(cfg.data.datamodule.student_views)) == privileged
    assert cfg.policy.on_policy == on_policy
    assert cfg.loss.lambda_ret == pytest.approx(lambda_ret)
    assert cfg.ablation.train_stage2 == trains
    # A sweep scores each variant by the method standing for it (launch/sweep_ablation.sh).
    swept = compose(config_name="evaluate",
                    overrides=[f"ablation={variant}", "evaluation.methods=[${ablation.method}]"])
    assert list(swept.evaluation.methods) == ["tracegs" if trains else "baseline"]
    # B..F share one Stage-1 checkpoint and the same Stage-2 budget.
    assert cfg.stage.init_adapter == compose(config_name="train").stage.init_adapter
    assert cfg.stage.max_steps == compose(config_name="train").stage.max_steps


def test_misspelt_override_names_the_field():
    with pytest.raises(ConfigCompositionException) as error:
        compose(config_name="train", overrides=["loss.lambda_rett=0.2"])
    assert "lambda_rett" in str(error.value.__cause__ or error.value)


@pytest.mark.parametrize(("override", "field"), [("stage.rollout_steps=many", "rollout_steps"),
                                                   ("backbone.schedule.train_loss_weighting=snr", "train_loss_weighting")])
def test_wrong_type_or_choice_names_the_field(override, field):
    with pytest.raises(ConfigCompositionException) as error:
        compose(config_name="train", overrides=[override])
    assert field in str(error.value.__cause__ or error.value)


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (["teacher.views=7"], "teacher.views"),
        (["stage.rollout_steps=40"], "stage.rollout_steps"),
        (["data.prepare.frames_per_clip=10"], "data.prepare.frames_per_clip"),
        (["deploy.repair_iters=[140,340,700]"], "deploy.repair_iters"),
        (["data.synthetic.test_seeds=[3,100]"], "data.synthetic.test_seeds"),
        (["data=dl3dv", "data.prepare.split=val"], "data.prepare.split"),  # test: captured held-out clips
        (["backbone.schedule.train_time_power=-1"], "backbone.schedule.train_time_power"),
        (["backbone.schedule.deploy_time_power=-1"], "backbone.schedule.deploy_time_power"),
        (["backbone.transformer.sigma_data=0"], "backbone.transformer.sigma_data"),
        (["backbone.schedule.noise_scale=0"], "backbone.schedule.noise_scale"),
        (["experiment=paper", "backbone.schedule.noise_scale=0.5"], "backbone.schedule.noise_scale"),
        (["backbone.schedule.noise_scale=0.2", "backbone.transformer.noise_scale=1.0"],
         "backbone.transformer.noise_scale"),  # the preconditioning must know the noise end
        (["backbone.sampler.temperature=1.5"], "backbone.sampler.temperature"),
        (["backbone.sampler.temperature=-0.1"], "backbone.sampler.temperature"),
        (["backbone.schedule.train_time_uniform_share=1.5"], "backbone.schedule.train_time_uniform_share"),
        (["backbone.transformer.prediction=residual"], "backbone.schedule.train_loss_weighting"),  # edm on a velocity head
        (["backbone.schedule.train_time_logit_normal=[1.0]"], "backbone.schedule.train_time_logit_normal"),
        (["backbone.schedule.train_time_logit_normal=[1.0,0]"], "backbone.schedule.train_time_logit_normal"),
        (["experiment=paper", "backbone.schedule.deploy_time_power=12"], "backbone.schedule.deploy_time_power"),
        (["evaluation.methods=[foo]"], "evaluation.methods"),
        (["training_data=dl3dvx"], "training_data"),
        (["report.datasets=[dl3dv,mip360]"], "report.datasets"),
        (["report.main_datasets=[dl3dv,nerfbuster]"], "report.main_datasets"),
        (["data=custom"], "training_data"),  # training runs on the training data (training_data=custom to train)
        (["data.prepare.dense_views=[]", "data.prepare.pseudo_target=dense"], "data.prepare.dense_views"),
        (["backbone.transformer.prediction=clean", "backbone.schedule.kind=vpred_ddim",
          "backbone.schedule.deploy_time_power=0"], "backbone.transformer.prediction"),
        # training deploys on validation scenes, never on a training (scene_000) or test scene (scene_100)
        (["stage.deployment_eval.scenes=[scene_050,scene_000]"], "stage.deployment_eval.scenes"),
        (["stage.deployment_eval.scenes=[scene_100]"], "stage.deployment_eval.scenes"),
    ],
)
def test_invalid_combination_names_the_field(overrides, field):
    cfg = compose(config_name="train", overrides=overrides)
    with pytest.raises(ConfigError) as error:
        validate(cfg)
    assert error.value.field == field
    assert f"'{field}'" in str(error.value)


def test_the_multi_step_restorer_takes_its_noise_end_from_the_schedule():
    cfg = compose(config_name="train", overrides=["backbone=tiny_diffusion", "backbone.schedule.noise_scale=0.17"])
    validate(cfg)
    assert cfg.backbone.transformer.noise_scale == 0.17


def test_deployment_eval_is_off_by_default_and_takes_validation_scenes():
    assert list(compose(config_name="train").stage.deployment_eval.scenes) == []
    cfg = compose(config_name="train", overrides=["stage.deployment_eval.scenes=[scene_050,scene_051]",
                                                  "stage.deployment_eval.every_n_steps=25"])
    validate(cfg)
    assert cfg.stage.deployment_eval.every_n_steps == 25 and list(cfg.stage.deployment_eval.views) == [3]


def test_the_learning_rate_search_scores_on_the_cache_that_prepare_writes_for_the_validation_scenes():
    """conf/hparams_search/stage2_lr.yaml names the validation cache by its path; it must be the folder
    ``tracegs-prepare data.prepare.split=val`` fills, under the command's settings."""
    for extra in ([], ["seed=3", "data.prepare.clips_per_scene=5"]):
        search = compose(config_name="train", overrides=["stage=stage2", "hparams_search=stage2_lr", *extra])
        validate(search)
        prepared = compose(config_name="prepare", overrides=["data.prepare.split=val", *extra])
        assert search.stage.held_out_eval.cache == prepared.data.prepare.cache_dir


def test_cli_prints_resolved_paper_config():
    """`--cfg job --resolve` of experiment=paper shows the paper's numbers (Sec. 4.1, supplement A)."""
    script = Path(sys.executable).with_name("tracegs-train")
    command = [str(script) if script.exists() else sys.executable, "experiment=paper", "stage=stage2",
               "--cfg", "job", "--resolve"]
    if not script.exists():
        command[1:1] = ["-m", "tracegs.cli.train"]
    out = subprocess.run(command, capture_output=True, text=True, check=True, timeout=120).stdout
    cfg = OmegaConf.create(out)
    assert cfg.backbone.lora.rank == 32 and cfg.backbone.lora.alpha == 32
    assert cfg.optimizer.lr == pytest.approx(1e-5)
    assert cfg.stage.batch_size == 2
    assert cfg.loss.lambda_align == 1.0 and cfg.loss.lambda_ret == pytest.approx(0.15)
    assert cfg.stage.rollout_steps == 10 and cfg.backbone.schedule.deploy_steps == 50
    assert cfg.deploy.total_iters == 30000 and list(cfg.deploy.repair_iters) == [7000, 17000, 27000]
    assert len(cfg.deploy.repair_iters) == 3  # N_r
    assert cfg.data.prepare.frames_per_clip == 49
    assert (cfg.data.source.height, cfg.data.source.width) == (480, 720)
    assert cfg.stage.max_steps == 2000 and cfg.optimizer.warmup_steps == 100
    assert cfg.experiment.stage1_steps == 500
    assert cfg.backbone.transformer.num_layers == 42
    assert cfg.data.prepare.fit.iterations == 30000  # the splat group reaches preparation and deployment


def test_cli_reports_bad_combination_in_one_line(tmp_path):
    script = Path(sys.executable).with_name("tracegs-train")
    result = subprocess.run([str(script), "stage.rollout_steps=40", f"paths.root_dir={tmp_path}"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines == [lines[0]] and "stage.rollout_steps" in lines[0]
    # Nothing but Hydra's own run log was written: no checkpoint, adapter or cache.
    written = [p for p in tmp_path.rglob("*") if p.is_file() and ".hydra" not in p.parts and p.suffix != ".log"]
    assert written == []


def test_the_embedded_default_restorer_is_multistep_with_tinys_encoders_and_ends_its_grid_near_clean():
    """The embedded default's restorer (backbone=tiny_diffusion): the one-step restorer's class, codec and encoders
    (the same caches), EDM-preconditioned, on a deployment grid whose last state before the clean end is at
    t <= 0.1."""
    from tracegs.pipeline.upstream import section
    from tracegs.restorer.schedules import build_schedule

    tiny, diffusion = (section(compose(config_name="train", overrides=overrides).backbone)
                       for overrides in (["experiment=embedded_onestep"], []))
    for part in ("name", "codec", "reference_encoder", "text_encoder", "lora"):
        assert getattr(tiny, part) == getattr(diffusion, part)
    assert diffusion.transformer.prediction == "preconditioned"
    grid = build_schedule(diffusion.schedule).timesteps()
    assert grid[0] == 1.0 and grid[-1] == 0.0 and float(grid[-2]) == pytest.approx(0.1)  # M = 10 uniform steps
    assert float(build_schedule(tiny.schedule).timesteps()[-2]) > 0.5  # the one-step restorer's last state


def test_a_and_stage1_read_the_first_clips_of_the_cache_stage2_reads_with_its_own_batch():
    """experiment.baseline_clips_per_scene limits what A and Stage 1 read of the one training cache, whose
    experiment.clips_per_scene clips Stage 2 reads whole, at experiment.stage2_batch_size."""
    reads = {stage: compose(config_name="train", overrides=[f"stage={stage}", "experiment.baseline_clips_per_scene=3",
                                                          "experiment.stage2_batch_size=1"])
             for stage in ("baseline", "stage1", "stage2")}
    assert {stage: cfg.data.datamodule.clips_per_scene for stage, cfg in reads.items()} == {
        "baseline": 3, "stage1": 3, "stage2": None}
    assert {stage: cfg.data.datamodule.batch_size for stage, cfg in reads.items()} == {
        "baseline": reads["baseline"].experiment.batch_size, "stage1": reads["stage1"].experiment.batch_size,
        "stage2": 1}
    # A reads its own pretraining scenes (the paper's data protocol), Stage 1 and 2 the one training cache; under
    # experiment=embedded_gt_targets A reads that cache too.
    assert reads["stage1"].data.datamodule.cache_dir == reads["stage2"].data.datamodule.cache_dir
    assert "-pretrain-" in reads["baseline"].data.datamodule.cache_dir
    gt = {stage: compose(config_name="train", overrides=[f"stage={stage}", "experiment=embedded_gt_targets"])
          for stage in ("baseline", "stage2")}
    assert len({cfg.data.datamodule.cache_dir for cfg in gt.values()}) == 1
