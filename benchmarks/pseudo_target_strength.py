"""How good the pseudo-targets are at each sampling strength: the frozen restorer A applied to R_d, scored against
ground truth on held-out clips (supplement A.4, "Pseudo-target generation"; ``data.prepare.pseudo_target_strength``).

Usage: ``.venv/bin/python benchmarks/pseudo_target_strength.py --weights <A>/baseline_transformer
--cache <held-out cache with the teacher condition> [--strengths 1,0.6,0.4,0.25,0.1] [--every 16] [overrides...]``

Every ``every``-th clip of the cache: R_d's codec latent restored by A (no adapter, guidance 1 as the embedded
default's pseudo-targets) at each strength with the clip's index as seed, decoded, the reference frames at the
ends dropped, PSNR against ground truth; R_d itself is the first row. Scene means first, then the mean over
scenes with its 95% bootstrap interval. Overrides compose the backbone as the commands do (default: the embedded
default's). The last line is one JSON object: ``r_d_psnr`` and ``strength_psnr`` (strength -> dB).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict

from tracegs.config.schema import register_configs
from tracegs.config.tree import ConfigTree
from tracegs.data import cache_keys
from tracegs.eval.clips import held_out_clips, load_clip, mean_psnr, trajectory_frames
from tracegs.eval.intervals import mean_interval
from tracegs.location import CONF_DIR
from tracegs.pipeline.upstream import section
from tracegs.restorer.build import build_backbone
from tracegs.restorer.sampler import RestorationPipeline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", required=True, help="variant A's transformer folder")
    parser.add_argument("--cache", required=True, help="a held-out cache holding R_d (the teacher condition)")
    parser.add_argument("--strengths", default="1,0.6,0.4,0.25,0.1")
    parser.add_argument("--every", type=int, default=16, help="score every n-th clip")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    strengths = [float(s) for s in args.strengths.split(",")]
    register_configs()
    cfg = ConfigTree.at(str(CONF_DIR)).compose("train", args.overrides)
    backbone_cfg = section(cfg.backbone)
    backbone_cfg.transformer.pretrained_path = args.weights
    backbone = build_backbone(backbone_cfg)
    pipeline = RestorationPipeline(backbone)
    teacher = cache_keys.condition_key(None)
    scores: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    clips = held_out_clips(args.cache)[::args.every]
    for index, clip in enumerate(clips):
        tensors = load_clip(clip)
        truth = trajectory_frames(tensors, cache_keys.GROUND_TRUTH)
        scores["R_d"][clip.scene].append(mean_psnr(trajectory_frames(tensors, teacher), truth))
        conditioning = [tensors[key].float().expand(1, -1, -1)
                        for key in (cache_keys.REF_2D, cache_keys.REF_3D, cache_keys.TEXT)]
        for strength in strengths:
            latents = pipeline.restore_latents(tensors[cache_keys.latent(teacher)].float()[None], *conditioning,
                                               seed=index, guidance_scale=1.0, strength=strength)
            restored = backbone.codec.decode(latents).cpu()[0, 1:-1]
            scores[str(strength)][clip.scene].append(mean_psnr(restored, truth))
        print(f"clip {index + 1}/{len(clips)}", flush=True)
    means = {row: mean_interval([sum(v) / len(v) for v in by_scene.values()]) for row, by_scene in scores.items()}
    print(f"{len(clips)} clips of {len(scores['R_d'])} scenes; PSNR (dB) against ground truth, 95% interval over "
          "scenes:")
    for row, interval in means.items():
        print(f"  {'R_d itself' if row == 'R_d' else f'A from R_d at strength {row}'}: {interval.format()}")
    print(json.dumps({"r_d_psnr": round(means["R_d"].mean, 2),
                      "strength_psnr": {row: round(i.mean, 2) for row, i in means.items() if row != "R_d"}}))


if __name__ == "__main__":
    main()
