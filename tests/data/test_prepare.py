"""End-to-end preparation on a tiny synthetic scene: from nothing, idempotent rerun, resume after a kill,
and bad input that fails before writing anything."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from PIL import Image
from safetensors import safe_open
from safetensors.torch import load_file
from scene_builders import all_files, differing_files, tiny_configs, write_scene

from tracegs.data.config import PrepareConfig, SceneSourceConfig
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.preparation.manifests import merge_manifests
from tracegs.data.preparation.plan import PrepareError, teacher_view_counts


def test_prepare_builds_the_cache_from_nothing(prepared):
    tmp, _, _, prepare, manifest_path = prepared
    manifest = json.loads(manifest_path.read_text())
    assert manifest["teacher_views"] == ["3", "6", "all"] and manifest["frames_stored"]
    entry = manifest["scenes"]["scene_000"]
    assert len(entry["clips"]) == 2
    scene_info = json.loads((tmp / "cache" / entry["scene_file"]).read_text())
    assert scene_info["clip_views"] == [3, 3]
    for rel in entry["clips"]:
        with safe_open(str(tmp / "cache" / rel), framework="pt") as f:
            keys = set(f.keys())
            latent = f.get_tensor("latent/s3_it8")
            poses = f.get_tensor("poses")
            metadata = f.metadata()
        assert {"latent/s3_it8", "latent/d3", "latent/d6", "latent/dall", "latent/target", "frames/gt",
                "frames/target", "frames/ref"} <= keys
        assert not keys & {"ref_2d", "ref_3d", "text"}  # in the scene files the clip indexes
        assert latent.shape[0] == 5 and poses.shape == (5, 4, 4)
        # Both clip ends are reference views of the clip's own 3-view set.
        a, b = json.loads(metadata["refs"])
        assert metadata["student_views"] == "3" and {a, b} <= set(scene_info["split"]["view_sets"]["3"])
        scene = tmp / "cache" / "scene_000"
        assert (scene / f"refs/view_{a:04d}.safetensors").is_file()
        assert (scene / f"refs/pair_{a:04d}_{b:04d}.safetensors").is_file()
        assert (scene / metadata["text_file"]).is_file()
    assert (tmp / "cache" / "scene_000" / "contact_sheet.png").is_file()
    psnr = entry["psnr_vs_gt"]
    assert set(psnr) == {"s3_it8", "d3", "d6", "dall"} and all(v > 5 for v in psnr.values())


def test_second_run_does_no_work(prepared, backbone):
    tmp, synthetic, source, prepare, manifest = prepared
    before = all_files(tmp)
    start = time.perf_counter()
    assert run_prepare(prepare, source, backbone, synthetic, progress=False) == manifest
    assert all_files(tmp) == before
    assert time.perf_counter() - start < 5.0


PREPARE_SCRIPT = (
    "import sys\n"
    "sys.path.insert(0, sys.argv[1])\n"
    "from dataclasses import replace\n"
    "from pathlib import Path\n"
    "from scene_builders import tiny_configs\n"
    "from tracegs.data.preparation.driver import run_prepare\n"
    "from tracegs.restorer.build import build_backbone\n"
    "from tracegs.restorer.config import BackboneConfig\n"
    "if __name__ == '__main__':\n"
    "    synthetic, source, _ = tiny_configs(Path(sys.argv[2]))\n"
    "    prepare = replace(tiny_configs(Path(sys.argv[3]))[2], workers=int(sys.argv[4]))\n"
    "    if int(sys.argv[5]):\n"
    "        prepare.fit = replace(prepare.fit, iterations=int(sys.argv[5]), snapshot_iters=[8, int(sys.argv[5])])\n"
    "    run_prepare(prepare, source, build_backbone(BackboneConfig()), synthetic, progress=False)\n"
)


def start_prepare(generated: Path, out: Path, workers: int = 1, fit_iterations: int = 0) -> subprocess.Popen:
    """``run_prepare`` of the tiny configs (scenes under ``generated``, products under ``out``) in a new process,
    with ``workers`` processes and, if non-zero, ``fit_iterations`` per fit."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-c", PREPARE_SCRIPT, str(Path(__file__).parent), str(generated),
                             str(out), str(workers), str(fit_iterations)], env=env, stderr=subprocess.PIPE, text=True)


def products(out: Path) -> list[Path]:
    return [p for part in ("work", "cache") for p in (out / part).rglob("*") if p.is_file()
            and not p.name.startswith(".")]


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_killed_run_reruns_to_identical_bytes(tmp_path, prepared, backbone, seed):
    """SIGKILL after a random number of finished products plus a random delay (seeded), then the same command:
    every fit and cache file equals the uninterrupted run's byte for byte, and finished fits are not redone."""
    reference, synthetic, source, _, _ = prepared
    total = len(products(reference))
    rng = random.Random(seed)
    kill_after, delay = rng.randrange(total), rng.uniform(0.0, 0.5)
    process = start_prepare(Path(synthetic.root).parent, tmp_path)
    deadline = time.monotonic() + 300
    while len(products(tmp_path)) < kill_after and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(delay)
    assert process.poll() is None, f"prepare ended before it could be killed: {process.stderr.read()[-2000:]}"
    process.send_signal(signal.SIGKILL)
    process.wait()
    process.stderr.close()
    finished_fits = {p: p.stat().st_mtime_ns for p in (tmp_path / "work").rglob("*.ply")}
    prepare = tiny_configs(tmp_path)[2]
    run_prepare(prepare, source, backbone, synthetic, progress=False)
    assert differing_files(reference / "work", tmp_path / "work") == []
    assert differing_files(reference / "cache", tmp_path / "cache") == []
    assert all(p.stat().st_mtime_ns == t for p, t in finished_fits.items()), "a finished fit was redone"


def child_pids(pid: int) -> set[int]:
    return {int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()}


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.slow  # two spawned workers import torch, then fit for a while: over a minute on a busy 2-core machine
@pytest.mark.skipif(sys.platform != "linux", reason="parent-death signal is Linux-only")
def test_workers_die_with_a_killed_parent(tmp_path, prepared):
    """SIGKILL of prepare while its two workers fit: the workers end at once, and write nothing more."""
    _, synthetic, _, _, _ = prepared
    process = start_prepare(Path(synthetic.root).parent, tmp_path, workers=2, fit_iterations=400)
    deadline = time.monotonic() + 300
    while not list((tmp_path / "work").rglob("*.ply")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.poll() is None, f"prepare ended before it could be killed: {process.stderr.read()[-2000:]}"
    workers = child_pids(process.pid)
    process.send_signal(signal.SIGKILL)
    process.wait()
    process.stderr.close()
    written = set((tmp_path / "work").rglob("*.ply"))
    # The workers (and multiprocessing's resource tracker, which exits when they have) take a moment to tear
    # down a process that holds torch, longer on a busy machine; an orphan would fit on for minutes.
    deadline = time.monotonic() + 10.0
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert workers and not any(alive(pid) for pid in workers)
    assert set((tmp_path / "work").rglob("*.ply")) == written


def test_the_last_shard_to_finish_merges_the_manifests(tmp_path, prepared, backbone):
    _, synthetic, source, _, _ = prepared
    cache = tmp_path / "cache"
    assert merge_manifests(cache, 2) is None  # no shard finished yet
    prepare = replace(tiny_configs(tmp_path)[2], num_shards=2, shard_index=0)
    shard = run_prepare(prepare, source, backbone, synthetic, progress=False)
    assert shard.name == "manifest_shard000_of002.json"
    assert merge_manifests(cache, 2) is None and not (cache / "manifest.json").exists()  # shard 1 still runs
    # Shard 1 finishes (its manifest: the same settings, another scene); shard 0, rerun, finds it and merges.
    first = json.loads(shard.read_text())
    (cache / "manifest_shard001_of002.json").write_text(json.dumps({**first, "scenes": {"scene_001": {}}}))
    assert run_prepare(prepare, source, backbone, synthetic, progress=False) == shard
    merged = (cache / "manifest.json").read_text()
    assert json.loads(merged) == {**first, "scenes": {"scene_000": first["scenes"]["scene_000"], "scene_001": {}}}
    stamp = (cache / "manifest.json").stat().st_mtime_ns
    assert merge_manifests(cache, 2) == cache / "manifest.json"  # merging again writes nothing new
    assert (cache / "manifest.json").read_text() == merged and (cache / "manifest.json").stat().st_mtime_ns == stamp
    (cache / "manifest_shard001_of002.json").write_text(json.dumps({**first, "version": -1, "scenes": {}}))
    with pytest.raises(PrepareError, match="settings differ"):
        merge_manifests(cache, 2)


@pytest.mark.parametrize("damage", ["missing_image_folder", "missing_image", "radial_camera", "too_many_views"])
def test_bad_input_fails_clearly_and_writes_nothing(tmp_path, backbone, damage):
    import pycolmap

    root, _ = write_scene(tmp_path / "scenes" / "ring", n=16)
    prepare = PrepareConfig(cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"),
                            pseudo_target="dense", dense_views=[None])
    expected: tuple[type[Exception], str]
    if damage == "missing_image_folder":
        for image in (root / "images").iterdir():
            image.unlink()
        (root / "images").rmdir()
        expected = (FileNotFoundError, "image folder not found")
    elif damage == "missing_image":
        (root / "images" / "img_007.png").unlink()
        expected = (FileNotFoundError, "img_007.png")
    elif damage == "radial_camera":
        model = pycolmap.Reconstruction(str(root / "sparse" / "0"))
        for camera in model.cameras.values():
            camera.model = pycolmap.CameraModelId.SIMPLE_RADIAL
            camera.params = [30.0, 18.0, 12.0, 0.01]
        model.write(str(root / "sparse" / "0"))
        expected = (PrepareError, "SIMPLE_RADIAL.*undistort")
    else:
        prepare = replace(prepare, student_views=[3, 6, 9], dense_views=[18])
        expected = (PrepareError, "asked for 18 training views, but of the scene.s 16 images 2 are held out.*14")
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    with pytest.raises(expected[0], match=expected[1]):
        run_prepare(prepare, source, backbone, progress=False)
    assert not (tmp_path / "cache").exists() and not (tmp_path / "work").exists()


@pytest.mark.parametrize("source_kind", ["dense", "restorer"])
def test_pseudo_target_sources(tmp_path, prepared, source_kind):
    """The dense rendering as target, or the frozen pretrained restorer itself (variant A, no adapter) applied
    to R_d as in the paper."""
    from tracegs.restorer.adapters import adapter_names
    from tracegs.restorer.build import build_backbone
    from tracegs.restorer.config import BackboneConfig

    _, synthetic, source, fitted, _ = prepared
    backbone = build_backbone(BackboneConfig())
    # Same work_dir: the fits are reused, only the clips are rendered and encoded again.
    prepare = replace(fitted, cache_dir=str(tmp_path / "cache"), pseudo_target=source_kind)
    manifest = json.loads(run_prepare(prepare, source, backbone, synthetic, progress=False).read_text())
    assert manifest["pseudo_target"] == source_kind
    with safe_open(str(tmp_path / "cache" / manifest["scenes"]["scene_000"]["clips"][0]), framework="pt") as f:
        target, dense = f.get_tensor("frames/target"), f.get_tensor("frames/dall")
        assert f.metadata()["pseudo_target"] == source_kind
    if source_kind == "dense":
        assert torch.equal(target, dense)
    else:
        assert target.shape == dense.shape and not torch.equal(target, dense)
    assert adapter_names(backbone.transformer) == []  # the generator is the base: no adapter is attached


def test_changed_settings_are_not_mistaken_for_finished_work(tmp_path, prepared, backbone):
    """Shards made with other settings (here: another pseudo-target source) are redone, fits are reused."""
    _, synthetic, source, fitted, _ = prepared
    cache = tmp_path / "cache"
    dense = replace(fitted, cache_dir=str(cache), pseudo_target="dense")
    run_prepare(dense, source, backbone, synthetic, progress=False)
    shard = cache / "scene_000" / "clip_000.safetensors"
    fits = {p: p.stat().st_mtime_ns for p in Path(fitted.work_dir).rglob("*.ply")}
    run_prepare(replace(dense, pseudo_target="gt"), source, backbone, synthetic, progress=False)
    with safe_open(str(shard), framework="pt") as f:
        assert f.metadata()["pseudo_target"] == "gt"
    assert {p: p.stat().st_mtime_ns for p in Path(fitted.work_dir).rglob("*.ply")} == fits


@pytest.mark.slow  # two worker processes import torch and fit (~12 s)
def test_parallel_workers_give_the_same_products(tmp_path, prepared, backbone):
    """Fits and clip renders in two worker processes (one thread each) equal the in-process run byte for byte:
    the fitted PLYs and every cache file (shards with their header metadata, scene files, manifest, sheet)."""
    _, synthetic, source, serial, _ = prepared
    parallel = replace(serial, cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"), workers=2)
    run_prepare(parallel, source, backbone, synthetic, progress=False)
    assert differing_files(Path(serial.work_dir), tmp_path / "work") == []
    assert differing_files(Path(serial.cache_dir), tmp_path / "cache") == []


def test_sparse_fits_stopped_at_the_last_student_snapshot_give_the_same_students(tmp_path, prepared, backbone):
    """``student_final_fits=False`` stops each sparse fit at its last student snapshot: every snapshot it keeps and
    every student condition equal the full fit's, only the sparse final snapshot (variant B's teacher) is gone."""
    _, synthetic, source, full, _ = prepared
    short = replace(full, cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"), student_final_fits=False)
    manifest = json.loads(run_prepare(short, source, backbone, synthetic, progress=False).read_text())
    full_fits = {str(p.relative_to(full.work_dir)) for p in Path(full.work_dir).rglob("*.ply")}
    short_fits = {str(p.relative_to(tmp_path / "work")) for p in (tmp_path / "work").rglob("*.ply")}
    sparse_final = {f for f in full_fits if "/fit_3_" in f and f.endswith(f"it{full.fit.iterations:06d}.ply")}
    assert len(sparse_final) == 1 and short_fits == full_fits - sparse_final
    assert differing_files(Path(full.work_dir), tmp_path / "work") == sorted(sparse_final)
    assert manifest["teacher_views"] == ["6", "all"]
    for rel in manifest["scenes"]["scene_000"]["clips"]:
        with safe_open(str(Path(full.cache_dir) / rel), framework="pt") as reference, \
                safe_open(str(tmp_path / "cache" / rel), framework="pt") as stopped:
            assert set(reference.keys()) - set(stopped.keys()) == {"latent/d3", "frames/d3"}
            assert all(torch.equal(reference.get_tensor(k), stopped.get_tensor(k)) for k in stopped.keys())


def test_a_cache_without_dense_views_scores_from_r_s_only(tmp_path, prepared, backbone):
    """``dense_views=[]`` (the demo's held-out cache): the student conditions and ground truth are the full
    cache's bytes, no dense view set is fitted or stored, and the contact sheet shows R_s, target and ground truth."""
    _, synthetic, source, full, _ = prepared
    bare = replace(full, cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"), dense_views=[])
    manifest = json.loads(run_prepare(bare, source, backbone, synthetic, progress=False).read_text())
    assert manifest["teacher_views"] == ["3"]  # the student set fitted to its final snapshot (variant B's teacher)
    assert {p.parent.name.split("_")[1] for p in (tmp_path / "work").rglob("*.ply")} == {"3"}
    for rel in manifest["scenes"]["scene_000"]["clips"]:
        with safe_open(str(Path(full.cache_dir) / rel), framework="pt") as reference, \
                safe_open(str(tmp_path / "cache" / rel), framework="pt") as bare_clip:
            assert set(reference.keys()) - set(bare_clip.keys()) == {"latent/d6", "frames/d6", "latent/dall",
                                                                      "frames/dall"}
            for key in ("frames/s3_it8", "frames/gt", "latent/s3_it8"):
                assert torch.equal(reference.get_tensor(key), bare_clip.get_tensor(key))
    sheet = Image.open(tmp_path / "cache" / "scene_000" / "contact_sheet.png")
    assert sheet.width == 3 * 48  # R_s, target, ground truth


def test_a_training_cache_holds_latents_only(tmp_path, prepared, backbone):
    """By default a training split's shards keep no frames (training reads latents); everything else, latents and
    the scene files they index, is the frame-keeping cache's bytes, and the contact sheet is still drawn."""
    _, synthetic, source, full, _ = prepared
    lean = replace(full, cache_dir=str(tmp_path / "cache"), store_frames=None)
    manifest = json.loads(run_prepare(lean, source, backbone, synthetic, progress=False).read_text())
    assert manifest["frames_stored"] is False
    for rel in manifest["scenes"]["scene_000"]["clips"]:
        with safe_open(str(Path(full.cache_dir) / rel), framework="pt") as kept, \
                safe_open(str(tmp_path / "cache" / rel), framework="pt") as latents_only:
            assert set(latents_only.keys()) == {k for k in kept.keys() if not k.startswith("frames/")}
            assert all(torch.equal(kept.get_tensor(k), latents_only.get_tensor(k)) for k in latents_only.keys())
    scene_files = sorted(p.relative_to(tmp_path / "cache") for p in (tmp_path / "cache").rglob("*/*/*.safetensors"))
    assert scene_files == sorted(p.relative_to(full.cache_dir) for p in Path(full.cache_dir).rglob("*/*/*.safetensors"))
    for rel in scene_files:
        kept, lean_file = load_file(str(Path(full.cache_dir) / rel)), load_file(str(tmp_path / "cache" / rel))
        assert kept.keys() == lean_file.keys() and all(torch.equal(kept[k], lean_file[k]) for k in kept)
    assert (tmp_path / "cache" / "scene_000" / "contact_sheet.png").is_file()


def test_shared_trajectories_restore_each_trajectory_once_for_every_k(tmp_path, prepared, backbone, monkeypatch):
    """``shared_trajectories``: each trajectory, drawn on the 3 views, serves K = 3 and 6 (consecutive clips with the
    same reference views and poses) and is restored into one pseudo-target that both clips hold, its R_d and target
    encoded once (each clip encodes its own R_s only); a resumed run that lost the second clip of a trajectory
    restores it again into the same bytes."""
    from tracegs.restorer.sampler import RestorationPipeline

    restorations, encoded = [], []
    restore = RestorationPipeline.restore_latents
    monkeypatch.setattr(RestorationPipeline, "restore_latents",
                        lambda self, *args, **kwargs: restorations.append(kwargs["seed"]) or restore(self, *args,
                                                                                                      **kwargs))
    encode = backbone.codec.encode
    monkeypatch.setattr(backbone.codec, "encode", lambda frames: encoded.append(len(frames)) or encode(frames))
    _, synthetic, source, fitted, _ = prepared
    # Its own work folder: the session's prepared one is the reference other tests compare whole folders with.
    shared = replace(fitted, cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"), student_views=[3, 6],
                     dense_views=[None], clips_per_scene=4, shared_trajectories=True, pseudo_target="restorer")
    manifest = json.loads(run_prepare(shared, source, backbone, synthetic, progress=False).read_text())
    scene = json.loads((tmp_path / "cache" / manifest["scenes"]["scene_000"]["scene_file"]).read_text())
    assert scene["clip_views"] == [3, 6, 3, 6]
    assert scene["clip_refs"][0] == scene["clip_refs"][1] and scene["clip_refs"][2] == scene["clip_refs"][3]
    assert len(restorations) == len(set(restorations)) == 2  # one pseudo-target per trajectory
    # Per trajectory its teacher conditions (R_d among them) and the target once, per clip its own student snapshots.
    assert sum(encoded) == 2 * (len(teacher_view_counts(shared)) + 1) + 4 * len(shared.student_snapshots)
    shards = [load_file(str(tmp_path / "cache" / rel)) for rel in manifest["scenes"]["scene_000"]["clips"]]
    for first, second in (shards[0], shards[1]), (shards[2], shards[3]):
        assert torch.equal(first["poses"], second["poses"])
        assert torch.equal(first["frames/target"], second["frames/target"])
        assert torch.equal(first["latent/target"], second["latent/target"])
    assert not torch.equal(shards[0]["frames/target"], shards[2]["frames/target"])
    assert {"latent/s3_it8", "latent/s6_it8"} == {k for k in (*shards[0], *shards[1]) if k.startswith("latent/s")}
    kept = {p.name: p.read_bytes() for p in (tmp_path / "cache" / "scene_000").glob("clip_*.safetensors")}
    (tmp_path / "cache" / "scene_000" / "clip_001.safetensors").unlink()
    restorations.clear()
    run_prepare(shared, source, backbone, synthetic, progress=False)
    assert len(restorations) == 1
    assert {p.name: p.read_bytes() for p in (tmp_path / "cache" / "scene_000").glob("clip_*.safetensors")} == kept


def test_shared_trajectories_need_nested_view_sets(tmp_path, prepared, backbone):
    """Trajectories drawn on the 3 views serve K = 4 only where the 3 views are among the 4: the linspace rule picks
    each set on its own (here views 1, 5, 11 and 1, 4, 7, 11), and preparation refuses in one line,
    before writing anything."""
    _, synthetic, source, fitted, _ = prepared
    shared = replace(fitted, cache_dir=str(tmp_path / "cache"), work_dir=str(tmp_path / "work"),
                     student_views=[3, 4], dense_views=[None], clips_per_scene=2, shared_trajectories=True)
    with pytest.raises(PrepareError, match=r"scene_000: views \[.*\] of the 3-view set are not in the 4-view set, "
                                           r"and data.prepare.shared_trajectories"):
        run_prepare(shared, replace(source, view_rule="linspace"), backbone, synthetic, progress=False)
    assert not (tmp_path / "cache").exists() and not (tmp_path / "work").exists()


def test_training_clips_reach_the_stages_only_through_the_frozen_restorer(tmp_path, prepared):
    """The paper's data protocol (the embedded default): a training cache holds no ground-truth tensor, its targets
    are the frozen restorer's output from R_d (other generator weights, other targets; the same student conditions),
    and a sample the stages read carries R_s, R_d, the references, the text and that target only."""
    from tracegs.data.config import DataModuleConfig
    from tracegs.data.datamodule import PairedClipDataModule
    from tracegs.restorer.build import build_backbone
    from tracegs.restorer.config import BackboneConfig

    _, synthetic, source, fitted, _ = prepared
    generator = build_backbone(BackboneConfig())
    other = build_backbone(BackboneConfig())
    with torch.no_grad():
        for parameter in other.transformer.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    shards = {}
    for name, backbone in (("A", generator), ("other", other)):
        prepare = replace(fitted, cache_dir=str(tmp_path / name), pseudo_target="restorer", store_frames=None)
        manifest = json.loads(run_prepare(prepare, source, backbone, synthetic, progress=False).read_text())
        assert manifest["pseudo_target"] == "restorer"
        clips = manifest["scenes"]["scene_000"]["clips"]
        shards[name] = tmp_path / name / clips[0]
        with safe_open(str(shards[name]), framework="pt") as f:
            assert not [key for key in f.keys() if key.rsplit("/", 1)[-1] == "gt"], "ground truth in a training cache"
    a, b = load_file(str(shards["A"])), load_file(str(shards["other"]))
    assert torch.equal(a["latent/s3_it8"], b["latent/s3_it8"]) and torch.equal(a["latent/dall"], b["latent/dall"])
    assert not torch.equal(a["latent/target"], b["latent/target"])
    data = PairedClipDataModule(DataModuleConfig(cache_dir=str(tmp_path / "A"), student_views=[3],
                                                 student_snapshots=[8], batch_size=1), teacher_views=None)
    data.setup("fit")
    sample = next(iter(data.train_dataloader()))
    def targets(name: str) -> list[torch.Tensor]:
        return [load_file(str(tmp_path / name / clip))["latent/target"].float() for clip in clips]

    assert any(torch.equal(sample["target"][0], target) for target in targets("A"))
    assert not any(torch.equal(sample["target"][0], target) for target in targets("other"))
