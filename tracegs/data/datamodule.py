"""``PairedClipDataModule``: paired student/teacher samples served from the prepared cache.

Sample dict (one clip; the default collate stacks a batch along a new first dim):

- ``student_cond`` (f, C, h, w) float32: codec latent of R_s (K sparse views, early snapshot)
- ``teacher_cond`` (f, C, h, w) float32: codec latent of R_d (the teacher's view set, final snapshot)
- ``target`` (f, C, h, w) float32: codec latent of the pseudo-target I_T
- ``ref_2d`` (R, D2), ``ref_3d`` (R, D3) float32: reference tokens of the clip's two reference views,
  identical for both roles (supplement A.2)
- ``text`` (L, Dt) float32: text embedding, already all-zero when the caption is dropped
- ``text_dropped`` () bool: the caption-dropout flag, sampled once per sample and shared by both roles
- ``scene`` str, ``clip`` int: provenance
- ``student_views`` int (K), ``teacher_views`` int (-1 = all training views), ``snapshot`` int

Every cached clip belongs to one student view count K (``data.prepare``), so the datamodule samples clips of the
configured K; each draw picks the clip's snapshot uniformly from the configured list and the dropout flag with
probability ``caption_dropout``, from a generator seeded by (seed, epoch, index): reproducible, yet a clip
gets a fresh choice every epoch. Validation draws are seeded by the index only. A sample opens its clip's
shard and the scene files it indexes with ``safe_open`` and reads only the tensors it returns.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import torch
from safetensors import SafetensorError, safe_open
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from tracegs.data import cache_keys
from tracegs.data.cache_keys import CACHE_VERSION, MANIFEST, condition_key
from tracegs.data.config import DataModuleConfig
from tracegs.data.splits import view_set_key
from tracegs.io import checksum_problem


def draw_seed_of(seed: int, epoch: int, index: int) -> int:
    """The caption-dropout draw of clip ``index`` in ``epoch``: distinct per (seed, epoch, index), and within
    the 63 bits ``torch.Generator.manual_seed`` takes for any 31-bit root seed."""
    return ((seed * 1_000_003 + epoch) * 1_000_033 + index) % (2**63 - 1)


class CacheError(ValueError):
    """The prepared cache is missing, inconsistent with the request, or damaged."""


def read_manifest(cache_dir: str | Path) -> dict:
    path = Path(cache_dir) / MANIFEST
    if not path.is_file():
        raise CacheError(f"{path}: no manifest; run prepare first")
    try:
        manifest = json.loads(path.read_text())
    except ValueError as error:
        raise CacheError(f"{path}: corrupt manifest ({error})") from error
    if manifest.get("version") != CACHE_VERSION:
        raise CacheError(f"{path}: cache layout version {manifest.get('version')}, this tracegs reads "
                         f"{CACHE_VERSION}; run prepare again into a new cache_dir")
    return manifest


def repeats_frames(images: list[int]) -> bool:
    """A held-out clip through captured cameras filled by repeating captured images (a padded clip:
    ``data.prepare.held_out_repeat_frames``)."""
    return len(set(images)) < len(images)


@dataclass(frozen=True)
class ClipRecord:
    """One cached clip as its header describes it: the tensors it holds, its student view count K, its two
    reference views and the scene files (reference tokens, text embedding) it indexes."""

    scene: str
    index: int
    path: Path
    views: int
    refs: tuple[int, int]
    text: str  # the text file of the clip's caption, relative to the scene folder
    keys: frozenset[str]
    metadata: dict[str, str]

    @property
    def scene_dir(self) -> Path:
        return self.path.parent

    def conditions(self) -> list[str]:
        """The clip's student conditions ``s{K}_it{snapshot}``, earliest snapshot first."""
        prefix = cache_keys.latent(cache_keys.student_prefix(self.views))
        return sorted((k.removeprefix("latent/") for k in self.keys if k.startswith(prefix)),
                      key=cache_keys.student_order)

    def captured_images(self) -> list[int] | None:
        """The captured image index of each frame (ends included) of a held-out clip through captured cameras,
        None for a clip with a rendered trajectory (every frame its own)."""
        images = self.metadata.get(cache_keys.META_CAPTURED_IMAGES)
        return None if images is None else json.loads(images)

    @property
    def padded(self) -> bool:
        images = self.captured_images()
        return images is not None and repeats_frames(images)

    def conditioning_files(self) -> list[tuple[Path, str]]:
        """(file, tensor key) of the 2D tokens of each reference view, the pair's 3D tokens and the text."""
        a, b = self.refs
        return [(self.scene_dir / cache_keys.view_tokens_file(a), cache_keys.REF_2D),
                (self.scene_dir / cache_keys.view_tokens_file(b), cache_keys.REF_2D),
                (self.scene_dir / cache_keys.pair_tokens_file(a, b), cache_keys.REF_3D),
                (self.scene_dir / self.text, cache_keys.TEXT)]


def clip_record(scene: str, index: int, path: Path) -> ClipRecord:
    """The header of a clip shard (no tensor data is read); ``CacheError`` naming a missing or unreadable one."""
    if not path.is_file():
        raise CacheError(f"{path}: shard listed in the manifest is missing; run prepare again with the same "
                         "settings to rebuild it")
    try:
        with safe_open(str(path), framework="pt") as f:
            keys, metadata = frozenset(f.keys()), f.metadata() or {}
        a, b = json.loads(metadata[cache_keys.META_REFS])
        views, text = int(metadata[cache_keys.META_VIEWS]), metadata[cache_keys.META_TEXT]
    except (SafetensorError, OSError, ValueError, KeyError, TypeError) as error:
        raise CacheError(f"{path}: corrupt shard ({error})") from error
    return ClipRecord(scene, index, path, views, (int(a), int(b)), text, keys, metadata)


def manifest_clips(cache_dir: str | Path, manifest: dict, scenes: list[str]) -> list[ClipRecord]:
    """The clip records of ``scenes``, in manifest order."""
    return [clip_record(scene, i, Path(cache_dir) / rel) for scene in scenes
            for i, rel in enumerate(manifest["scenes"][scene]["clips"])]


def verify_file(path: Path, required: list[str] | None = None) -> None:
    """Refuse (``CacheError`` naming the file) a missing or unreadable safetensors file, one that lacks a
    ``required`` key, and one whose ``required`` tensors (default: all) differ from the checksums written with
    them: training on changed bytes would silently give another adapter."""
    if not path.is_file():
        raise CacheError(f"{path}: file of the cache is missing; run prepare again with the same settings")
    try:
        with safe_open(str(path), framework="pt") as f:
            keys = set(f.keys())
    except (SafetensorError, OSError, ValueError) as error:
        raise CacheError(f"{path}: corrupt shard ({error})") from error
    missing = [k for k in required or [] if k not in keys]
    if missing:
        raise CacheError(f"{path}: shard lacks {missing}; re-run prepare with these view sets / snapshots")
    problem = checksum_problem(path, required)
    if problem:
        raise CacheError(f"{path}: {problem}; run prepare again with the same settings to rebuild it")


def verify_clip(record: ClipRecord, required: list[str] | None = None) -> None:
    """``verify_file`` of a clip's ``required`` tensors (default: all) and of the scene files it indexes."""
    verify_file(record.path, required)
    for path, key in record.conditioning_files():
        verify_file(path, [key])


def read_tensors(path: Path, keys: list[str]) -> dict[str, torch.Tensor]:
    """Only the tensors ``keys`` of one safetensors file (``get_tensor`` reads each one's bytes, nothing else)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            return {key: f.get_tensor(key) for key in keys}
    except (SafetensorError, OSError, ValueError) as error:
        raise CacheError(f"{path}: corrupt shard ({error})") from error


def read_conditioning(record: ClipRecord) -> dict[str, torch.Tensor]:
    """The clip's reference tokens and text embedding gathered from the scene files: ``ref_2d`` is the two
    views' tokens concatenated (first reference first, as the encoder returns them for the pair)."""
    first, second, pair, text = [read_tensors(path, [key])[key] for path, key in record.conditioning_files()]
    return {cache_keys.REF_2D: torch.cat([first, second]), cache_keys.REF_3D: pair, cache_keys.TEXT: text}


# The teacher_views of a stage that reads no teacher condition (variant A).
NO_TEACHER = "no teacher"


class PairedClipDataset(Dataset):
    """Clips of the given scenes whose student view count is listed (with ``clips_per_scene``, only among each
    scene's first that many); items are indices or ``(index, draw_seed)`` pairs from ``EpochSampler``. A sample
    reads only the tensors it returns."""

    def __init__(self, cache_dir: str | Path, scenes: list[str], manifest: dict, student_views: list[int],
                 student_snapshots: list[int], teacher_views: int | None, caption_dropout: float, seed: int,
                 clips_per_scene: int | None = None):
        self.cache_dir = Path(cache_dir)
        self.clips = [c for c in manifest_clips(cache_dir, manifest, scenes)
                      if c.views in student_views and (clips_per_scene is None or c.index < clips_per_scene)]
        if not self.clips:
            raise CacheError(f"{self.cache_dir}: no clip of {student_views} student views in scenes {scenes}")
        self.student_snapshots = list(student_snapshots)
        self.teacher_views = teacher_views
        self.teacher_key = None if teacher_views is NO_TEACHER else condition_key(teacher_views)
        self.caption_dropout = caption_dropout
        self.seed = seed
        for clip in self.clips:
            required = [cache_keys.latent(condition_key(clip.views, s)) for s in student_snapshots]
            required += [cache_keys.latent(key) for key in (self.teacher_key, cache_keys.TARGET) if key is not None]
            verify_clip(clip, required)

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, item: int | tuple[int, int]) -> dict:
        index, draw_seed = item if isinstance(item, tuple) else (item, draw_seed_of(self.seed, 0, item))
        clip = self.clips[index]
        generator = torch.Generator().manual_seed(draw_seed)
        snapshot = self.student_snapshots[int(torch.randint(len(self.student_snapshots), (), generator=generator))]
        dropped = bool(torch.rand((), generator=generator) < self.caption_dropout)
        student, target = cache_keys.latent(condition_key(clip.views, snapshot)), cache_keys.latent(cache_keys.TARGET)
        teacher = None if self.teacher_key is None else cache_keys.latent(self.teacher_key)
        latents = read_tensors(clip.path, [key for key in (student, teacher, target) if key is not None])
        conditioning = read_conditioning(clip)
        text = conditioning[cache_keys.TEXT].float()
        return {
            "student_cond": latents[student].float(),
            **({} if teacher is None else {"teacher_cond": latents[teacher].float()}),
            "target": latents[target].float(),
            "ref_2d": conditioning[cache_keys.REF_2D].float(),
            "ref_3d": conditioning[cache_keys.REF_3D].float(),
            # Supplement A.2: a dropped caption is an all-zero embedding (not the encoding of ""), and the
            # same embedding goes to both roles.
            "text": torch.zeros_like(text) if dropped else text,
            "text_dropped": torch.tensor(dropped),
            "scene": clip.scene,
            "clip": clip.index,
            "student_views": clip.views,
            "teacher_views": -1 if self.teacher_views in (None, NO_TEACHER) else int(self.teacher_views),
            "snapshot": snapshot,
        }


class EpochSampler(DistributedSampler):
    """Indices of this rank (shuffled per epoch), each paired with a draw seed from (seed, epoch, index).

    Lightning calls ``set_epoch`` every epoch, so the student view count, snapshot and caption-dropout flag
    are redrawn each epoch yet reproducible. Being a ``DistributedSampler`` itself, it also partitions the
    clips across DDP ranks, and Lightning does not wrap it (a wrapper would hide ``set_epoch`` from it).
    """

    def __init__(self, dataset: Dataset, seed: int, shuffle: bool = True):
        distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
        replicas = torch.distributed.get_world_size() if distributed else 1
        rank = torch.distributed.get_rank() if distributed else 0
        super().__init__(dataset, num_replicas=replicas, rank=rank, shuffle=shuffle, seed=seed)
        self.skip = 0  # leading samples of this epoch's order to leave out once (mid-epoch resume)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        skip, self.skip = self.skip, 0
        for position, index in enumerate(super().__iter__()):
            if position >= skip:
                yield index, draw_seed_of(self.seed, self.epoch, index)


class ResumableDataLoader(DataLoader):
    """A ``DataLoader`` over an ``EpochSampler`` whose position inside an epoch survives a checkpoint.

    Lightning stores ``state_dict()`` of every loader that has one in its checkpoints and hands it back
    through ``load_state_dict`` before the resumed epoch is iterated. Without it a run resumed mid-epoch
    would start that epoch over and train on different batches than the uninterrupted run. Written here
    because torch's DataLoader keeps no position and torchdata's StatefulDataLoader would add a dependency
    for what is a counter: the sampler's order is a pure function of (seed, epoch), so the position is
    the whole state. Lightning does not prefetch from sized loaders, so batches handed out equal batches
    trained on when a checkpoint is written.
    """

    def __init__(self, dataset: Dataset, sampler: EpochSampler, **kwargs):
        super().__init__(dataset, sampler=sampler, **kwargs)
        self._batches_yielded = 0
        self._resume_at = 0

    def __iter__(self):
        self._batches_yielded, self._resume_at = self._resume_at, 0
        self.sampler.skip = self._batches_yielded * self.batch_size
        for batch in super().__iter__():
            self._batches_yielded += 1
            yield batch

    def state_dict(self) -> dict[str, int]:
        return {"batches": self._batches_yielded}

    def load_state_dict(self, state: dict[str, int]) -> None:
        # A checkpoint written after an epoch's last batch resumes at the start of the next epoch.
        self._resume_at = state["batches"] if state["batches"] < len(self) else 0


class PairedClipDataModule(L.LightningDataModule):
    """Train/val split by scene over the prepared cache; see the module docstring for the sample dict.

    ``teacher_views`` comes from the ``teacher`` config group (None = all training views, 3 for the
    non-privileged variant B, 12 / 18 for variants C / D); :data:`NO_TEACHER` for variant A, which reads R_s and
    the target only (its pretraining scenes fit no teacher).
    """

    def __init__(self, cfg: DataModuleConfig, teacher_views: int | None = None):
        super().__init__()
        self.cfg = cfg
        self.teacher_views = teacher_views
        self.train_set: PairedClipDataset | None = None
        self.val_set: PairedClipDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        cfg = self.cfg
        manifest = read_manifest(cfg.cache_dir)
        available = manifest.get("teacher_views", [])
        if self.teacher_views is not NO_TEACHER and view_set_key(self.teacher_views) not in available:
            raise CacheError(f"{Path(cfg.cache_dir) / MANIFEST}: teacher views {view_set_key(self.teacher_views)} "
                             f"not prepared (have {available})")
        unknown = [s for s in cfg.val_scenes if s not in manifest["scenes"]]
        if unknown:
            raise CacheError(f"data.val_scenes {unknown} are not in the cache {cfg.cache_dir}")
        train = [s for s in manifest["scenes"] if s not in cfg.val_scenes]
        if not train:
            raise CacheError(f"{cfg.cache_dir}: every scene is a validation scene; nothing to train on")

        def dataset(scenes: list[str]) -> PairedClipDataset:
            return PairedClipDataset(cfg.cache_dir, scenes, manifest, cfg.student_views, cfg.student_snapshots,
                                     self.teacher_views, cfg.caption_dropout, cfg.seed, cfg.clips_per_scene)

        self.train_set = dataset(train)
        self.val_set = dataset(list(cfg.val_scenes)) if cfg.val_scenes else None

    def train_dataloader(self) -> DataLoader:
        return ResumableDataLoader(self.train_set, EpochSampler(self.train_set, self.cfg.seed),
                                   batch_size=self.cfg.batch_size, num_workers=self.cfg.num_workers,
                                   drop_last=False, persistent_workers=self.cfg.num_workers > 0)

    def val_dataloader(self) -> DataLoader | list:
        if self.val_set is None:
            return []
        return DataLoader(self.val_set, batch_size=self.cfg.batch_size, num_workers=self.cfg.num_workers,
                          shuffle=False)
