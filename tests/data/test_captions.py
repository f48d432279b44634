"""Clip captions: one rule for prepare and deployment; BLIP-2 on the first frame of R_s when configured."""

from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path

import pytest
import sentencepiece
import torch
from safetensors import safe_open
from scene_builders import tiny_configs

from tracegs.data.captions import clip_caption
from tracegs.data.colmap import load_scene
from tracegs.data.config import CaptionConfig, SceneSourceConfig
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.splits import split_scene
from tracegs.deploy.config import RefinementConfig
from tracegs.deploy.refine import render_round_clips
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.ply import load_ply


def tiny_blip2(root: Path) -> Path:
    """A randomly initialised BLIP-2 (ViT + Q-Former + OPT) with a sentencepiece tokenizer, in the
    transformers layout ``Blip2ForConditionalGeneration.from_pretrained`` reads."""
    from transformers import (
        Blip2Config,
        Blip2ForConditionalGeneration,
        Blip2Processor,
        Blip2QFormerConfig,
        Blip2VisionConfig,
        BlipImageProcessor,
        OPTConfig,
        T5Tokenizer,
    )

    corpus = ["a photo of a scene", "a garden with a table and a bicycle", "a red cube on a wooden floor"] * 10
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(sentence_iterator=iter(corpus), model_writer=model, vocab_size=48,
                                             model_type="unigram", pad_id=0, eos_id=1, unk_id=2, bos_id=3,
                                             hard_vocab_limit=False, minloglevel=2)
    spiece = root / "spiece.model"
    spiece.write_bytes(model.getvalue())
    pieces = sentencepiece.SentencePieceProcessor(model_file=str(spiece))
    tokenizer = T5Tokenizer(vocab=[(pieces.id_to_piece(i), pieces.get_score(i)) for i in range(len(pieces))],
                            extra_ids=0, unk_id=pieces.unk_id())
    size = len(tokenizer)
    config = Blip2Config(
        vision_config=Blip2VisionConfig(hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                        num_attention_heads=2, image_size=32, patch_size=8).to_dict(),
        qformer_config=Blip2QFormerConfig(hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                          num_attention_heads=2, encoder_hidden_size=16, vocab_size=size).to_dict(),
        text_config=OPTConfig(vocab_size=size + 1, hidden_size=16, ffn_dim=32, num_hidden_layers=1,
                              num_attention_heads=2, word_embed_proj_dim=16, pad_token_id=0, bos_token_id=3,
                              eos_token_id=1).to_dict(),
        num_query_tokens=4)
    config.image_token_index = size
    torch.manual_seed(0)
    blip2 = Blip2ForConditionalGeneration(config)
    out = root / "blip2"
    blip2.save_pretrained(out)
    Blip2Processor(image_processor=BlipImageProcessor(size={"height": 32, "width": 32}), tokenizer=tokenizer,
                   num_query_tokens=4).save_pretrained(out)
    return out


@pytest.fixture(params=["deterministic", "blip2"])
def captions(request, tmp_path) -> CaptionConfig:
    if request.param == "deterministic":
        return CaptionConfig(fallback="a scene without caption.txt")
    return CaptionConfig(blip2_path=str(tiny_blip2(tmp_path)), max_new_tokens=4)


def test_prepare_and_deployment_caption_clips_by_one_rule(colmap_scene, backbone, captions, tmp_path):
    """A scene without caption.txt: the caption prepare caches for a clip is ``clip_caption`` of the first frame
    of its R_s, and deployment captions its clip of the same rendering identically."""
    root, _ = colmap_scene
    _, _, prepare = tiny_configs(tmp_path)
    prepare = replace(prepare, captions=captions, pseudo_target="dense")
    source = SceneSourceConfig(root=str(root.parent), preset="custom", height=32, width=48)
    manifest = json.loads(run_prepare(prepare, source, backbone, progress=False).read_text())
    shard = Path(prepare.cache_dir) / manifest["scenes"]["ring"]["clips"][0]
    with safe_open(str(shard), framework="pt") as handle:
        cached = handle.metadata()["caption"]
        first = handle.get_tensor("frames/s3_it8")[0].float() / 255.0
    assert cached == clip_caption(captions, first, None)
    if captions.blip2_path is None:
        assert cached == "a scene without caption.txt"
    else:
        assert cached and cached != captions.fallback  # BLIP-2 described the frame
    # Deployment from the same snapshot and captured views: each clip caption follows the same rule.
    scene = load_scene(source, "ring")
    captured = [View(image=scene.load_image(i), camera=scene.cameras[i])
                for i in split_scene(scene, source, [3]).views(3)]
    snapshot = next(Path(prepare.work_dir).glob("ring/fit_3_*/it000008.ply"))
    fitter = GaussianFitter(load_ply(snapshot), prepare.fit, 1.0)
    fitter.iteration = 8
    refine_cfg = RefinementConfig(trajectory=prepare.trajectory, captions=captions, max_clips_per_round=1)
    (clip,) = render_round_clips(fitter, captured, 0, refine_cfg, prepare.fit, "", torch.Generator())
    assert clip.caption == clip_caption(captions, clip.frames[0], None)
    if captions.blip2_path is None:
        assert clip.caption == cached
