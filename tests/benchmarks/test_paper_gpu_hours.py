"""benchmarks/paper_gpu_hours.py: the work of each paper-scale command, counted from the config the command
composes (the GPU hours are these counts times seconds per unit that the script states as estimates)."""

from __future__ import annotations

import sys
from pathlib import Path

from hydra import compose

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import paper_gpu_hours as gpu  # noqa: E402  (a script directory, not a package)

PAPER = ["experiment=paper", "trainer=ddp"]


def test_stage2_counts_every_rank_and_rollout_state(hydra_context):
    """Supplement: 2,000 iterations, batch 2 on each of 4 GPUs, N = 10 student forwards with gradient and 10
    teacher forwards per sample (unguided in training)."""
    work = gpu.train_work(compose(config_name="train", overrides=[*PAPER, "stage=stage2", "ablation=F"]))
    assert work.training_forwards == work.forwards == 2000 * 2 * 4 * 10
    stage1 = gpu.train_work(compose(config_name="train", overrides=[*PAPER, "stage=stage1"]))
    assert stage1.training_forwards == 2 * 500 * 2 * 4 and stage1.forwards == 0  # both roles carry gradient
    assert gpu.train_work(compose(config_name="train", overrides=[*PAPER, "stage=baseline"])).gpu_hours() == 0


def test_evaluation_counts_guided_restorations_of_every_gsfixer_window(hydra_context):
    """Mip-NeRF 360's nine published scenes at 3/6/9 views: per scene and K, N_r = 3 rounds of GSFixer's 7 windows
    (gsfixer/extrapolation/outpaint/sparse.py l. 245, whatever K), each a 49-frame clip restored over M = 50 guided
    steps (two forwards), and the J = 30k 3DGS iterations."""
    cfg = compose(config_name="evaluate", overrides=[*PAPER, "data=mipnerf360", "evaluation.methods=[baseline]"])
    scenes = gpu.test_scenes(cfg, dl3dv=28)
    assert scenes == 9
    work = gpu.evaluate_work(cfg, scenes)
    assert work.forwards == 9 * 3 * 3 * 7 * 50 * 2
    assert work.rendered_frames == 9 * 3 * 3 * 7 * 49
    assert work.fit_iterations + work.refine_iterations == 9 * 3 * 30_000


def test_training_cache_counts_every_teacher_fit_and_pseudo_target(hydra_context):
    """Per training scene: the 3/6/9-view fits and the 12/18/all-view teachers at 30k iterations, and "150 paired
    clips" as 25 trajectories x 3 K x 2 snapshots: 75 clips (each captioned), 150 student conditions, and 25
    pseudo-targets, each R_d restored once (and captioned) over M = 50 guided steps; a trajectory's four teacher
    conditions (B's 3-view final snapshot, 12, 18, all views) and its target encoded once, each clip's two R_s on
    their own; without shared trajectories every clip is restored and encodes all of its conditions."""
    cfg = compose(config_name="prepare", overrides=PAPER)
    work = gpu.prepare_work(cfg, scenes=1)
    assert work.fit_iterations == 6 * 30_000
    assert len(gpu.clip_views(cfg)) * len(cfg.data.prepare.student_snapshots) == 150
    assert work.forwards == 25 * 50 * 2 and work.decodes == 25 and work.captions == 75 + 25
    assert work.encodes == 75 * 2 + 25 * (4 + 1)
    apart = gpu.prepare_work(compose(config_name="prepare", overrides=[*PAPER, "data.prepare.shared_trajectories=false"]),
                             scenes=1)
    assert apart.forwards == 75 * 50 * 2 and apart.decodes == 75 and apart.captions == 75
    assert apart.encodes == 75 * (2 + 4 + 1)


def test_tables_1_2_evaluate_nerfbusters_which_table_3_leaves_out(hydra_context):
    """Paper Table 2 compares on Mip-NeRF 360 and NeRFBusters, Table 3 on DL3DV and Mip-NeRF 360: NeRFBusters' twelve
    published captures get one evaluation of 3DGS, A and F (the students trained on DL3DV) and its Tables 1/2
    report, and no step of the Table 3 sweep."""
    rows, _ = gpu.plan([], train_scenes=112, dl3dv_scenes=28)
    labels = [label for label, _, _ in rows]
    assert [label for label in labels if label.startswith("Tables 1/2")] == [
        "Tables 1/2 on dl3dv", "Tables 1/2 on mipnerf360", "Tables 1/2 on nerfbusters"]
    on_nerfbusters = [(label, command, work) for label, command, work in rows if "data=nerfbusters" in command]
    assert [label for label, _, _ in on_nerfbusters] == ["evaluate 3DGS, A and F on nerfbusters (Tables 1/2)",
                                                        "Tables 1/2 on nerfbusters"]
    (_, evaluate, work), (_, report, _) = on_nerfbusters
    assert evaluate.startswith("tracegs-evaluate ") and "ablation=" not in evaluate and "report.kind=main" in report
    cfg = compose(config_name="evaluate", overrides=[*PAPER, "data=nerfbusters"])
    assert gpu.test_scenes(cfg, dl3dv=28) == 12 and work == gpu.evaluate_work(cfg, 12) and work.gpu_hours() > 0
    # Table 3 and Fig. 6 stay on DL3DV and Mip-NeRF 360.
    assert [label for label in labels if "nerfbusters" in label] == [label for label, _, _ in on_nerfbusters]
    assert any("data=mipnerf360" in command and "ablation=A," in command for _, command, _ in rows)
    # Where the sweep evaluated A and F (DL3DV, Mip-NeRF 360), Tables 1/2 read them and evaluate 3DGS alone.
    for dataset in ("dl3dv", "mipnerf360"):
        (_, evaluate, work), (_, report, _) = [row for row in rows if f"on {dataset} " in f"{row[0]} "
                                               and "Tables 1/2" in row[0]]
        assert evaluate.endswith("evaluation.methods=[3dgs]") and work.forwards == 0 < work.fit_iterations
        assert report.endswith("report.kind=main report.main_from_sweep=true")


def test_the_paper_scope_prepares_only_fs_teacher(hydra_context):
    """The paper's five days cover one student (F): its cache fits the all-view set to 30k and the 3/6/9-view sets
    only to their last student snapshot (17k), and restores the same 25 pseudo-targets per scene."""
    work = gpu.scope_prepare_work([], train_scenes=1)
    assert work.fit_iterations == 30_000 + 3 * 17_000
    assert work.forwards == 25 * 50 * 2


def test_measured_units_replace_the_estimates_and_name_their_source():
    record = {"device": {"name": "GPU X"}, "restorer": {"rollout_step": {"seconds": 1.0}},
              "vae": {"vae_encode": {"seconds": 2.0}},
              "stage2": {"batch_size": 2, "rollout_steps": 10, "iteration": {"seconds": 100.0},
                         "iterations": [{"seconds": 100.0}]}}
    unit, sources = gpu.UnitSeconds.measured(record)
    # 20 states per iteration, 5 s each: a 1 s teacher forward and 4 s of student forward and backward.
    assert unit.transformer_forward == 1.0 and unit.training_forward_factor == 4.0 and unit.vae_encode == 2.0
    assert unit.vae_decode == gpu.UnitSeconds().vae_decode and sources["vae_decode"] == "assumed (one A100)"
    assert sources["transformer_forward"] == "measured on GPU X"
    # One iteration timed is the first, which allocates AdamW's state: the source says so.
    assert "first iteration only" in sources["training_forward_factor"]
    record["stage2"]["iterations"].append({"seconds": 99.0})
    assert gpu.UnitSeconds.measured(record)[1]["training_forward_factor"] == "measured on GPU X (Stage 2 as configured)"
