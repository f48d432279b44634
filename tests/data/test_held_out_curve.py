"""Stage 2's learning curve on held-out clips (``stage.held_out_eval``): the student scored before its first step
(beside A and the Stage-1 adapter it starts from), every n steps and at the end, without changing what it learns."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from tracegs.data.config import DataModuleConfig
from tracegs.errors import ConfigError
from tracegs.eval.clips import clip_restoration_psnr
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline
from tracegs.training.config import (
    HeldOutEvalConfig,
    OptimizerConfig,
    StageConfig,
    TrainConfig,
    TrainerConfig,
)
from tracegs.training.run import train_stage


def config(tmp, cache, name: str, steps: int, out: str, **stage) -> TrainConfig:
    return TrainConfig(
        stage=StageConfig(name=name, max_steps=steps, batch_size=2, rollout_steps=2, **stage),
        optimizer=OptimizerConfig(lr=3e-3, warmup_steps=1),
        trainer=TrainerConfig(enable_progress_bar=False, log_every_n_steps=1),
        backbone=BackboneConfig(),
        data=DataModuleConfig(cache_dir=str(cache), student_views=[3], student_snapshots=[8], caption_dropout=0.0),
        output_dir=str(tmp / out),
    )


def test_stage2_scores_its_student_on_held_out_clips_as_it_trains(prepared):
    tmp, cache = prepared[0], prepared[0] / "cache"
    base = train_stage(config(tmp, cache, "baseline", 1, "curve_a"))
    aligned = train_stage(config(tmp, cache, "stage1", 1, "curve_s1", base_weights=str(base)))
    stage2 = dict(base_weights=str(base), init_adapter=str(aligned))
    plain = train_stage(config(tmp, cache, "stage2", 3, "curve_plain", **stage2))
    scored = train_stage(config(tmp, cache, "stage2", 3, "curve_scored", **stage2,
                                held_out_eval=HeldOutEvalConfig(cache=str(cache), every_n_steps=2)))

    # The same student bytes with and without the scoring (its restorations draw from their own generators).
    assert (scored / "adapter_model.safetensors").read_bytes() == (plain / "adapter_model.safetensors").read_bytes()
    curve = json.loads((tmp / "curve_scored" / "held_out_curve.json").read_text())
    assert [point["step"] for point in curve["points"]] == [0, 2, 3]
    assert (tmp / "curve_scored" / "held_out_curve.png").stat().st_size > 0
    references = curve["references"]
    assert set(references) == {"input", "A", "initial"}
    assert curve["points"][0]["mean"] == references["initial"]["mean"]  # the student starts as the Stage-1 adapter
    assert set(curve["points"][-1]["per_scene"]) == {"scene_000"}
    # A's line is the held-out clip table's A: the bare base, same clips, conditions and seeds.
    cfg = BackboneConfig()
    trained_a = build_backbone(replace(cfg, transformer=replace(cfg.transformer, pretrained_path=str(base))))
    table = clip_restoration_psnr({"A": RestorationPipeline(trained_a)}, cache, progress=False)
    assert references["A"]["mean"] == pytest.approx(table["mean"]["A"], abs=1e-4)
    assert references["input"]["mean"] == pytest.approx(table["mean"]["input"], abs=1e-6)


def test_a_missing_held_out_cache_is_named_before_training(prepared):
    tmp, cache = prepared[0], prepared[0] / "cache"
    cfg = config(tmp, cache, "stage1", 1, "curve_missing",
                 held_out_eval=HeldOutEvalConfig(cache=str(tmp / "nowhere")))
    with pytest.raises(ConfigError, match="stage.held_out_eval.cache"):
        train_stage(cfg)
    with pytest.raises(ValueError, match="stage.held_out_eval.every_n_steps"):
        HeldOutEvalConfig(cache=str(cache), every_n_steps=0)

