"""PairedClipDataModule over a prepared tiny cache: sample dict, teacher setting, caption dropout shared by
both roles, split by scene, and clear errors for damaged or mismatched caches."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from tracegs.data.config import DataModuleConfig
from tracegs.data.datamodule import CacheError, PairedClipDataModule


def module(cache: Path, teacher_views: int | None = None, **kwargs) -> PairedClipDataModule:
    cfg = DataModuleConfig(cache_dir=str(cache), student_views=[3], student_snapshots=[8], batch_size=2, **kwargs)
    dm = PairedClipDataModule(cfg, teacher_views=teacher_views)
    dm.setup("fit")
    return dm


def two_scene_cache(prepared, tmp_path: Path) -> Path:
    """A copy of the prepared cache whose one scene also appears under a second name."""
    cache = tmp_path / "cache"
    shutil.copytree(prepared[0] / "cache", cache)
    manifest = json.loads((cache / "manifest.json").read_text())
    shutil.copytree(cache / "scene_000", cache / "scene_001")
    entry = manifest["scenes"]["scene_000"]
    manifest["scenes"]["scene_001"] = {**entry, "clips": [c.replace("scene_000", "scene_001") for c in entry["clips"]]}
    (cache / "manifest.json").write_text(json.dumps(manifest))
    return cache


def test_sample_dict_matches_the_cache(prepared, backbone):
    """Latents from the clip's shard; reference tokens and text gathered from the scene files equal what the frozen
    encoders give for the clip's reference pair and caption (the 2D tokens stored per view, the 3D per pair)."""
    from tracegs.data.colmap import load_scene

    tmp, _, source, _, _ = prepared
    cache = tmp / "cache"
    dm = module(cache, teacher_views=None, caption_dropout=0.0)
    batch = next(iter(dm.train_dataloader()))
    path = cache / "scene_000" / f"clip_{int(batch['clip'][0]):03d}.safetensors"
    shard = load_file(str(path))
    with safe_open(str(path), framework="pt") as f:
        metadata = f.metadata()
    f, c, h, w = shard["latent/target"].shape
    assert batch["student_cond"].shape == (2, f, c, h, w) and batch["student_cond"].dtype == torch.float32
    torch.testing.assert_close(batch["student_cond"][0], shard["latent/s3_it8"].float())
    torch.testing.assert_close(batch["teacher_cond"][0], shard["latent/dall"].float())
    torch.testing.assert_close(batch["target"][0], shard["latent/target"].float())
    scene = load_scene(source, "scene_000")
    refs = torch.stack([scene.load_image(i) for i in json.loads(metadata["refs"])])
    ref_2d, ref_3d = backbone.reference_encoder(refs[None])
    assert torch.equal(batch["ref_2d"][0], ref_2d[0].half().float())
    assert torch.equal(batch["ref_3d"][0], ref_3d[0].half().float())
    assert torch.equal(batch["text"][0], backbone.text_encoder.encode([metadata["caption"]])[0].half().float())
    assert batch["teacher_views"].tolist() == [-1, -1] and batch["student_views"].tolist() == [3, 3]
    assert batch["snapshot"].tolist() == [8, 8] and batch["scene"] == ["scene_000", "scene_000"]
    assert not batch["text_dropped"].any()


def test_a_missing_scene_file_names_itself(prepared, tmp_path):
    cache = two_scene_cache(prepared, tmp_path)
    text = next((cache / "scene_001" / "text").glob("*.safetensors"))
    text.unlink()
    with pytest.raises(CacheError, match=f"{text}: file of the cache is missing"):
        module(cache)


def test_a_cache_of_another_layout_version_is_refused(prepared, tmp_path):
    cache = two_scene_cache(prepared, tmp_path)
    manifest = json.loads((cache / "manifest.json").read_text())
    (cache / "manifest.json").write_text(json.dumps({**manifest, "version": 1}))
    with pytest.raises(CacheError, match="cache layout version 1, this tracegs reads 2; run prepare again"):
        module(cache)


def test_teacher_view_setting_selects_the_dense_condition(prepared):
    cache = prepared[0] / "cache"
    sample = module(cache, teacher_views=3).train_set[0]
    shard = load_file(str(cache / "scene_000" / "clip_000.safetensors"))
    torch.testing.assert_close(sample["teacher_cond"], shard["latent/d3"].float())
    assert sample["teacher_views"] == 3
    with pytest.raises(CacheError, match="teacher views 12 not prepared"):
        module(cache, teacher_views=12)


def test_caption_dropout_zeroes_the_shared_text_and_is_seeded(prepared):
    cache = prepared[0] / "cache"
    always = module(cache, caption_dropout=1.0).train_set[0]
    assert always["text_dropped"] and not always["text"].any()
    dataset = module(cache, caption_dropout=0.5).train_set
    flags = [bool(dataset[(0, seed)]["text_dropped"]) for seed in range(200)]
    assert 60 < sum(flags) < 140  # about half, a fresh draw per draw seed
    assert flags == [bool(dataset[(0, seed)]["text_dropped"]) for seed in range(200)]  # reproducible
    for seed, dropped in enumerate(flags[:20]):
        sample = dataset[(0, seed)]
        assert bool(sample["text"].any()) != dropped


def test_epochs_redraw_but_stay_reproducible(prepared):
    dm = module(prepared[0] / "cache", caption_dropout=0.5)
    sampler = dm.train_dataloader().sampler
    epoch0 = list(sampler)
    sampler.set_epoch(1)
    epoch1 = list(sampler)
    sampler.set_epoch(0)
    assert list(sampler) == epoch0 and epoch0 != epoch1


def test_loader_resumes_inside_an_epoch_where_its_state_says(prepared, tmp_path):
    """A checkpointed loader position brings back the rest of that epoch, then whole epochs again."""
    cache = two_scene_cache(prepared, tmp_path)  # 4 clips: 2 batches per epoch

    def clips(batches) -> list[tuple[str, ...]]:
        return [tuple(f"{s}/{c}" for s, c in zip(b["scene"], b["clip"].tolist())) for b in batches]

    loader = module(cache).train_dataloader()
    loader.sampler.set_epoch(3)
    uninterrupted = clips(loader)
    iterator = iter(loader)
    first = next(iterator)
    state = loader.state_dict()
    assert state == {"batches": 1}

    restarted = module(cache).train_dataloader()
    restarted.load_state_dict(state)
    restarted.sampler.set_epoch(3)
    assert clips([first]) + clips(restarted) == uninterrupted
    assert clips(restarted) == uninterrupted  # the skip applies to the resumed epoch only
    finished = module(cache).train_dataloader()
    finished.load_state_dict({"batches": 2})  # saved after an epoch's last batch: next epoch starts whole
    finished.sampler.set_epoch(3)
    assert clips(finished) == uninterrupted


def test_split_by_scene(prepared, tmp_path):
    cache = two_scene_cache(prepared, tmp_path)
    dm = module(cache, val_scenes=["scene_001"])
    assert {clip.scene for clip in dm.train_set.clips} == {"scene_000"}
    assert {clip.scene for clip in dm.val_set.clips} == {"scene_001"}
    assert next(iter(dm.val_dataloader()))["scene"] == ["scene_001", "scene_001"]
    with pytest.raises(CacheError, match="scene_009"):
        module(cache, val_scenes=["scene_009"])


def test_corrupt_shard_names_the_file(prepared, tmp_path):
    cache = two_scene_cache(prepared, tmp_path)
    shard = cache / "scene_001" / "clip_001.safetensors"
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])
    with pytest.raises(CacheError, match="scene_001/clip_001.safetensors: corrupt shard"):
        module(cache)
    shard.write_bytes(b"\xff" * 64)
    with pytest.raises(CacheError, match="clip_001.safetensors: corrupt shard"):
        module(cache)


def test_lightning_redraws_dropout_each_epoch(prepared):
    """Inside a real Trainer the sampler's epoch advances, so a clip's dropout flag is redrawn per epoch."""
    import lightning as L

    seen: list[tuple[int, int, bool]] = []

    class Recorder(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.weight = torch.nn.Parameter(torch.zeros(()))

        def training_step(self, batch, batch_idx):
            for clip, dropped in zip(batch["clip"].tolist(), batch["text_dropped"].tolist()):
                seen.append((self.current_epoch, clip, dropped))
            return (self.weight * batch["target"].mean()).square()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.0)

    dm = PairedClipDataModule(DataModuleConfig(cache_dir=str(prepared[0] / "cache"), student_views=[3],
                                               student_snapshots=[8], batch_size=1, caption_dropout=0.5))
    trainer = L.Trainer(max_epochs=6, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(Recorder(), datamodule=dm)
    per_epoch = [sorted((c, d) for e, c, d in seen if e == epoch) for epoch in range(6)]
    assert all(len(p) == 2 for p in per_epoch)
    assert len({tuple(p) for p in per_epoch}) > 1


def test_a_sample_reads_only_the_tensors_it_returns(prepared, monkeypatch):
    """Per sample: the student, teacher and target latents of its own shard, the two views' 2D tokens, the pair's
    3D tokens and the caption's embedding; nothing of other clips, no frames."""
    from tracegs.data import datamodule

    dataset = module(prepared[0] / "cache").train_set
    fetched: list[tuple[str, str]] = []
    real = datamodule.safe_open

    class Recording:
        def __init__(self, path, framework):
            self.path, self.handle = path, real(path, framework=framework)

        def __enter__(self):
            self.inner = self.handle.__enter__()
            return self

        def __exit__(self, *exc):
            self.handle.__exit__(*exc)

        def get_tensor(self, key):
            fetched.append((Path(self.path).relative_to(dataset.cache_dir / "scene_000").as_posix(), key))
            return self.inner.get_tensor(key)

    monkeypatch.setattr(datamodule, "safe_open", Recording)
    clip = dataset.clips[1]
    dataset[(1, 0)]
    a, b = clip.refs
    assert sorted(fetched) == sorted([
        ("clip_001.safetensors", "latent/s3_it8"), ("clip_001.safetensors", "latent/dall"),
        ("clip_001.safetensors", "latent/target"), (f"refs/view_{a:04d}.safetensors", "ref_2d"),
        (f"refs/view_{b:04d}.safetensors", "ref_2d"), (f"refs/pair_{a:04d}_{b:04d}.safetensors", "ref_3d"),
        (clip.text, "text")])


def test_clips_of_the_listed_student_view_counts_are_served(tmp_path):
    """A cache with a 3-view and a 6-view clip (written by prepare's writer): each clip serves its own K's
    snapshot, ``student_views`` picks the clips and ``clips_per_scene`` keeps only each scene's first ones."""
    from tracegs.data.cache_keys import CACHE_VERSION
    from tracegs.data.preparation.shards import EncodedClip, write_clip

    g = torch.Generator().manual_seed(0)
    paths = []
    for index, views in enumerate((3, 6)):
        tensors = {f"latent/{name}": torch.randn(2, 4, 3, 3, generator=g).half()
                   for name in (f"s{views}_it8", "dall", "target")}
        clip = EncodedClip(tensors, views, (0, views - 1), f"clip {index}",
                           (torch.randn(2, 5, generator=g).half(), torch.randn(2, 5, generator=g).half()),
                           torch.randn(4, 7, generator=g).half(), torch.randn(3, 6, generator=g).half())
        paths.append(str(write_clip(tmp_path / "s", index, clip, {}, "random").relative_to(tmp_path)))
        (tmp_path / "manifest.json").write_text(json.dumps({"version": CACHE_VERSION, "teacher_views": ["all"],
                                                            "scenes": {"s": {"clips": paths}}}))
    for listed, first, served in (([6], None, [6]), ([3, 6], None, [3, 6]), ([3, 6], 1, [3])):
        cfg = DataModuleConfig(cache_dir=str(tmp_path), student_views=listed, student_snapshots=[8],
                               clips_per_scene=first)
        dm = PairedClipDataModule(cfg)
        dm.setup("fit")
        samples = [dm.train_set[i] for i in range(len(dm.train_set))]
        assert [s["student_views"] for s in samples] == served
        for sample in samples:
            shard = load_file(str(tmp_path / "s" / f"clip_{sample['clip']:03d}.safetensors"))
            assert torch.equal(sample["student_cond"], shard[f"latent/s{sample['student_views']}_it8"].float())
