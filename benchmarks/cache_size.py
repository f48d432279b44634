"""Bytes the paired-clip cache stores per clip and reads per training step, at the paper's shapes.

Usage: ``.venv/bin/python benchmarks/cache_size.py [--out DIR]``

Shapes come from the composed ``experiment=paper`` config (``conf/experiment/paper.yaml``,
``conf/backbone/cogvideox5b.yaml``): CogVideoX latents of ``sample_frames`` frames (temporal factor
``temporal_compression_ratio``) at ``sample_height x sample_width`` with ``latent_channels`` channels in
``data.prepare.latent_dtype``; 2D / 3D reference tokens of ``ref_2d_dim`` / ``ref_3d_dim`` features on the DINOv2 /
VGGT patch grid of a ``frame_height x frame_width`` view (``reference_grid``, GSFixer's preprocessing); a text
embedding of ``max_text_seq_length x text_embed_dim``. The conditions of a clip of each student view count K are
``prepare.clip_condition_keys`` of the composed ``data.prepare``; frames are stored as ``prepare.frames_stored``
says for a training cache.

Stored bytes: one clip of every K, random tensors of those shapes, goes through prepare's own writer
(``prepare.write_clip``: the shard and the scene files it indexes) into a temporary folder. Per clip is the mean
shard size over a scene's clips (``clip_view_counts``: how many clips each K gets) plus the scene files
amortised over ``clips_per_scene``: one 2D-token file per view of the largest sparse set (the sets are nested),
one 3D-token file per reference pair a round of each K uses (``reference_pairs``), and one text file per clip
(paper scale captions each clip with BLIP-2, so captions are counted as all distinct: an upper bound).

Bytes read per step: the real datamodule (``PairedClipDataModule``, teacher = all views) serves one batch of
``batch_size`` from that folder. Its ``safe_open`` is wrapped to record every file opened and every tensor
fetched; bytes read are, per file opened, its 8-byte length and header, plus, per tensor fetched, the extent
between its ``data_offsets`` in that file's header. The ratio divides them by the batch's tensor bytes at the
precision they are stored in (elements of every tensor of the batch times the cached element size): 1 means the
step reads nothing it does not use. Setup (checksum verification, once per process) is not part of a step.

The last line is one JSON object: ``cache_mb_per_clip_paper`` (MB = 1e6 bytes; goal <= 20),
``read_ratio_per_step`` (goal <= 2) and ``cache_tb_112_scenes`` (the paper's 112 DL3DV scenes).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.data import cache_keys, datamodule
from tracegs.data.cache_keys import MANIFEST
from tracegs.data.config import DataModuleConfig, PrepareConfig
from tracegs.data.datamodule import PairedClipDataModule
from tracegs.data.preparation.manifests import manifest_header
from tracegs.data.preparation.plan import clip_condition_keys, clip_view_counts, frames_stored
from tracegs.data.preparation.shards import EncodedClip, write_clip
from tracegs.restorer.encoders import reference_grid
from tracegs.splat.trajectory import reference_pairs

SCENE = "scene_000"
PAPER_SCENES = 112  # paper Sec. 4.1: the training set is 112 DL3DV scenes
MB, TB = 1e6, 1e12


def paper_config():
    """(backbone, data.prepare as PrepareConfig, frame size, batch size) of ``experiment=paper``."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        cfg = compose(config_name="prepare", overrides=["experiment=paper"])
    prepare = OmegaConf.to_object(cfg.data.prepare)
    assert isinstance(prepare, PrepareConfig)
    return (cfg.backbone, prepare, (int(cfg.experiment.frame_height), int(cfg.experiment.frame_width)),
            int(cfg.experiment.batch_size))


def paper_clip(backbone, prepare: PrepareConfig, frame_size: tuple[int, int], views: int, refs: tuple[int, int],
               caption: str, generator: torch.Generator) -> EncodedClip:
    """A K-view clip of random tensors at the paper's shapes, as ``save_clip`` hands it to ``write_clip``."""
    t = backbone.transformer
    dtype = getattr(torch, prepare.latent_dtype)
    latent = ((t.sample_frames - 1) // t.temporal_compression_ratio + 1, t.latent_channels, t.sample_height,
              t.sample_width)
    tokens = reference_grid(OmegaConf.to_object(backbone.reference_encoder), *frame_size)
    per_view = tokens[0] * tokens[1]

    def random(*shape: int) -> torch.Tensor:
        return torch.randn(shape, generator=generator).to(dtype)

    names = [*clip_condition_keys(prepare, views), cache_keys.TARGET]
    tensors = {cache_keys.latent(name): random(*latent) for name in names}
    if frames_stored(prepare):
        tensors.update({cache_keys.frames(name): torch.zeros(prepare.frames_per_clip, 3, *frame_size,
                                                            dtype=torch.uint8) for name in names})
    tensors[cache_keys.POSES] = torch.eye(4).expand(prepare.frames_per_clip, 4, 4).contiguous()
    tensors[cache_keys.INTRINSICS] = torch.eye(3).expand(prepare.frames_per_clip, 3, 3).contiguous()
    return EncodedClip(tensors, views, refs, caption, (random(per_view, t.ref_2d_dim), random(per_view, t.ref_2d_dim)),
                       random(2 * per_view, t.ref_3d_dim), random(t.max_text_seq_length, t.text_embed_dim))


def header_extents(path: Path) -> tuple[int, dict]:
    """(bytes of the length field and header, tensor name -> (begin, end) byte offsets) of a safetensors file."""
    with open(path, "rb") as handle:
        length = int.from_bytes(handle.read(8), "little")
        header = json.loads(handle.read(length))
    return 8 + length, {k: tuple(v["data_offsets"]) for k, v in header.items() if k != "__metadata__"}


class RecordingOpen:
    """``safe_open`` that records the files it opens and the tensors fetched from them."""

    opened: list[str] = []
    fetched: list[tuple[str, str]] = []
    real = staticmethod(datamodule.safe_open)

    def __init__(self, path: str, framework: str):
        self.path = path
        self.handle = RecordingOpen.real(path, framework=framework)
        RecordingOpen.opened.append(path)

    def __enter__(self):
        self.inner = self.handle.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.handle.__exit__(*exc)

    def keys(self):
        return self.inner.keys()

    def metadata(self):
        return self.inner.metadata()

    def get_tensor(self, key: str) -> torch.Tensor:
        RecordingOpen.fetched.append((self.path, key))
        return self.inner.get_tensor(key)


def bytes_read() -> int:
    """Header bytes of every file opened plus the data extent of every tensor fetched."""
    total = 0
    for path in RecordingOpen.opened:
        total += header_extents(Path(path))[0]
    for path, key in RecordingOpen.fetched:
        begin, end = header_extents(Path(path))[1][key]
        total += end - begin
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="folder for the written clips (default: a temporary one)")
    args = parser.parse_args()
    backbone, prepare, frame_size, batch_size = paper_config()
    generator = torch.Generator().manual_seed(0)
    with tempfile.TemporaryDirectory(dir=args.out) as tmp:
        cache = Path(tmp)
        scene_dir = cache / SCENE
        ladder = list(range(max(prepare.student_views)))  # nested view sets: V_3 within V_6 within V_9
        shards, shard_bytes = [], {}
        for index, views in enumerate(prepare.student_views):
            refs = (ladder[0], ladder[views - 1])
            clip = paper_clip(backbone, prepare, frame_size, views, refs, f"caption of clip {index}", generator)
            path = write_clip(scene_dir, index, clip, {"scene": SCENE, "clip": str(index)}, "benchmark")
            shards.append(str(path.relative_to(cache)))
            shard_bytes[views] = path.stat().st_size
        sizes = {kind: next(scene_dir.glob(pattern)).stat().st_size
                 for kind, pattern in (("view", "refs/view_*"), ("pair", "refs/pair_*"), ("text", "text/*"))}
        counts = clip_view_counts(prepare, SCENE)
        clips = len(counts)
        pairs = sum(min(counts.count(k), len(reference_pairs(k, None, generator))) for k in prepare.student_views)
        scene_files = {"view": max(prepare.student_views) * sizes["view"], "pair": pairs * sizes["pair"],
                       "text": clips * sizes["text"]}
        shard_mean = sum(shard_bytes[k] for k in counts) / clips
        per_clip = shard_mean + sum(scene_files.values()) / clips
        print(f"paper shapes: {clips} clips per scene, student K {prepare.student_views} "
              f"(clips per K {[counts.count(k) for k in prepare.student_views]}), frames stored: "
              f"{frames_stored(prepare)}, latents {prepare.latent_dtype}")
        for views in prepare.student_views:
            print(f"  shard of a {views}-view clip: {shard_bytes[views] / MB:.2f} MB "
                  f"({len(clip_condition_keys(prepare, views)) + 1} latents)")
        print(f"  scene files: {max(prepare.student_views)} view files of {sizes['view'] / MB:.2f} MB, {pairs} pair "
              f"files of {sizes['pair'] / MB:.2f} MB, {clips} text files of {sizes['text'] / MB:.2f} MB "
              f"= {sum(scene_files.values()) / clips / MB:.2f} MB per clip")
        print(f"stored per clip: {per_clip / MB:.2f} MB (goal <= 20); {PAPER_SCENES} scenes: "
              f"{per_clip * clips * PAPER_SCENES / TB:.2f} TB")

        manifest = {**manifest_header(prepare, backbone.name),
                    "scenes": {SCENE: {"scene_file": f"{SCENE}/scene.json", "clips": shards}}}
        (cache / MANIFEST).write_text(json.dumps(manifest))
        module = PairedClipDataModule(DataModuleConfig(
            cache_dir=str(cache), student_views=list(prepare.student_views),
            student_snapshots=list(prepare.student_snapshots), batch_size=batch_size, seed=0), teacher_views=None)
        module.setup("fit")  # verification: once per process, not per step
        datamodule.safe_open = RecordingOpen
        try:
            batch = next(iter(module.train_dataloader()))
        finally:
            datamodule.safe_open = RecordingOpen.real
        itemsize = torch.finfo(getattr(torch, prepare.latent_dtype)).bits // 8
        used = sum(v.numel() * itemsize for v in batch.values()
                   if isinstance(v, torch.Tensor) and v.is_floating_point())
        read = bytes_read()
    print(f"one training step (batch {batch_size}): {len(RecordingOpen.opened)} files opened, "
          f"{len(RecordingOpen.fetched)} tensors fetched, {read / MB:.2f} MB read for {used / MB:.2f} MB of batch "
          f"tensors: ratio {read / used:.3f} (goal <= 2)")
    print(json.dumps({"cache_mb_per_clip_paper": round(per_clip / MB, 2), "read_ratio_per_step": round(read / used, 4),
                      "cache_tb_112_scenes": round(per_clip * clips * PAPER_SCENES / TB, 3),
                      "read_mb_per_step": round(read / MB, 2)}))


if __name__ == "__main__":
    main()
