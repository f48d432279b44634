"""The cache's files of one clip (layout: ``tracegs.data.cache_keys``): its shard and the scene files it
indexes, written atomically with checksums and the settings they were made with, and the checks that tell a
finished unit from one to redo.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open

from tracegs.content import names_and_bytes_digest
from tracegs.data import cache_keys
from tracegs.data.config import PrepareConfig
from tracegs.data.datamodule import CacheError, clip_record
from tracegs.data.preparation.plan import settings_digest
from tracegs.errors import InputFileError
from tracegs.io import checksum_problem, non_finite_keys, read_safetensors, save_safetensors_atomic
from tracegs.products import Product, read_values
from tracegs.restorer.build import Backbone
from tracegs.restorer.config import sections_not_in_cache


@dataclass
class EncodedClip:
    """What one clip stores: its shard's tensors (latents, poses, frames when kept) and the conditioning it
    indexes in the scene files (2D tokens per reference view, 3D tokens of the pair, the caption's text)."""

    tensors: dict[str, torch.Tensor]
    views: int
    refs: tuple[int, int]
    caption: str
    ref_2d: tuple[torch.Tensor, torch.Tensor]
    ref_3d: torch.Tensor
    text: torch.Tensor

    def scene_files(self) -> list[tuple[str, str, torch.Tensor]]:
        """(file relative to the scene folder, tensor key, tensor) of every scene file the clip indexes."""
        a, b = self.refs
        return [(cache_keys.view_tokens_file(a), cache_keys.REF_2D, self.ref_2d[0]),
                (cache_keys.view_tokens_file(b), cache_keys.REF_2D, self.ref_2d[1]),
                (cache_keys.pair_tokens_file(a, b), cache_keys.REF_3D, self.ref_3d),
                (cache_keys.text_file(self.caption), cache_keys.TEXT, self.text)]


@functools.cache
def generator_digest(path: str) -> str:
    """The pseudo-target generator's content digest, read once per process: clip_settings runs once per scene, and
    at paper scale the folder is GSFixer's transformer (about 11 GB)."""
    return names_and_bytes_digest(path)


def clip_settings(cfg: PrepareConfig, backbone: Backbone) -> str:
    """Digest of everything a clip shard depends on besides the scene (stored in the shard's metadata): the
    fields a cache reads (tracegs.products), less the backbone sections its pseudo-targets do not need."""
    made_with = read_values(backbone.cfg, Product.prepare)
    for section in sections_not_in_cache(cfg.pseudo_target):
        made_with.pop(section)
    generator = made_with.get("transformer", {})
    if generator.get("pretrained_path"):
        # The pseudo-target generator (variant A: at the embedded scale a product under the run's root) is known by
        # its content, not its path: a copied or moved root makes the same clips and finds them finished.
        generator["pretrained_path"] = generator_digest(generator["pretrained_path"])
    return settings_digest({"prepare": read_values(cfg, Product.prepare), "backbone": made_with})


def scene_file_is_valid(path: Path, key: str, settings: str) -> bool:
    """A scene file exists, holds ``key`` with the bytes its checksum was written for, and was made with
    ``settings`` (another run's tokens or embeddings are not this run's)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            if key not in f.keys() or (f.metadata() or {}).get("settings") != settings:
                return False
    except (SafetensorError, OSError, ValueError):
        return False
    return checksum_problem(path, [key]) is None


def write_clip(scene_dir: Path, index: int, clip: EncodedClip, metadata: dict[str, str], settings: str) -> Path:
    """Write one clip: first the scene files it indexes that are not there yet (reference tokens, text), then
    its shard, so a finished shard always finds its scene files. Every file atomic, with checksums."""
    for rel, key, tensor in clip.scene_files():
        if not scene_file_is_valid(scene_dir / rel, key, settings):
            save_safetensors_atomic({key: tensor}, scene_dir / rel, {"settings": settings})
    path = scene_dir / cache_keys.clip_file(index)
    save_safetensors_atomic(clip.tensors, path, {
        **metadata, "caption": clip.caption, cache_keys.META_VIEWS: str(clip.views),
        cache_keys.META_REFS: json.dumps(list(clip.refs)), cache_keys.META_TEXT: cache_keys.text_file(clip.caption),
        "settings": settings})
    return path


def shard_is_valid(path: Path, settings: str | None = None, images: list[int] | None = None) -> bool:
    """A shard exists, is readable, matches the checksum written with it, holds only finite numbers, (if
    given) was made with ``settings`` and records the captured ``images`` of a held-out clip (a capture order
    that changed, or a shard from before the record, is not this clip), and the scene files it indexes are
    there and intact.

    Atomic writes make partial files impossible, but a disk or a user can still change their bytes, a shard
    made with other settings is not a finished unit of this run, and one with NaN would poison training.
    """
    try:
        tensors, metadata = read_safetensors(path, fix="")
        record = clip_record(path.parent.name, 0, path)
    except (InputFileError, CacheError):
        return False
    if checksum_problem(path):
        return False
    made_with = metadata.get("settings")
    if not (cache_keys.latent(cache_keys.TARGET) in tensors and (settings is None or made_with == settings)
            and (images is None or record.captured_images() == images) and not non_finite_keys(tensors)):
        return False
    return all(scene_file_is_valid(file, key, made_with) for file, key in record.conditioning_files())


def read_shard_psnr(path: Path) -> dict[str, float]:
    with safe_open(str(path), framework="pt") as f:
        return json.loads(f.metadata().get("psnr_vs_gt", "{}"))


def remove_unindexed_scene_files(scene_dir: Path, shard_paths: list[Path]) -> None:
    """Delete reference-token and text files no clip indexes any more (left by a run with other settings)."""
    indexed = {path for shard in shard_paths for path, _ in clip_record(scene_dir.name, 0, shard).conditioning_files()}
    for folder in {path.parent for path in indexed}:
        for path in folder.glob("*.safetensors"):
            if path not in indexed:
                path.unlink()
