"""`tracegs-weights`: the declared releases fill exactly the folders the paper scale reads, `--dry-run` lists them
offline, and `--check` passes a tree recorded in the released layouts and fails on one changed byte, naming it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from tracegs.cluster.weights import MANIFEST, RELEASES, weight_paths
from tracegs.config.schema import register_configs
from tracegs.location import CONF_DIR

WEIGHTS = "/weights"


def tracegs_weights(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tracegs.cli.weights", *args], capture_output=True, text=True,
                          env={**os.environ, "HF_HUB_OFFLINE": "1"}, timeout=120)


def test_the_releases_are_the_folders_the_paper_scale_reads():
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=paper", f"paths.weights_dir={WEIGHTS}"])
    targets = {Path(WEIGHTS, release.target) for release in RELEASES}
    read = {name: Path(path) for name, path in weight_paths(cfg).items() if path is not None}
    assert len(read) == 8
    for name, path in read.items():
        assert any(path == target or target in path.parents for target in targets), (name, path)
    assert all(any(path == t or t in path.parents for path in read.values()) for t in targets)  # nothing extra


def test_dry_run_lists_every_repository_offline():
    run = tracegs_weights("--dry-run", "--offline")
    assert run.returncode == 0, run.stderr
    for release in RELEASES:
        assert f"{release.repo or release.url}" in run.stdout
    assert "vgg16-397923af.pth  553,433,881 B (declared)" in run.stdout
    assert "VGGT-1B/model.safetensors  size unknown" in run.stdout
    assert run.stdout.splitlines()[-1].startswith("total: 553,433,881 B known;")


def fake_tree(root: Path) -> None:
    """Each release's declared files (a few bytes each) in its released layout."""
    for release in RELEASES:
        names = [name for name, _ in release.files] or ["config.json", "diffusion_pytorch_model.safetensors"]
        for name in names:
            path = root / release.target / name if name else root / release.target
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(f"{release.name}/{name}".encode())
    (root / "dinov2-with-registers-large" / ".cache" / "huggingface").mkdir(parents=True)  # the Hub's bookkeeping
    (root / "dinov2-with-registers-large" / ".cache" / "huggingface" / "x.lock").write_text("")


def test_check_passes_a_recorded_tree_and_names_a_changed_byte(tmp_path):
    fake_tree(tmp_path)
    assert "no readable manifest" in tracegs_weights("--check", "--weights-dir", str(tmp_path)).stderr
    recorded = tracegs_weights("--record", "--weights-dir", str(tmp_path))
    assert recorded.returncode == 0, recorded.stderr
    assert ".cache" not in (tmp_path / MANIFEST).read_text()
    passed = tracegs_weights("--check", "--weights-dir", str(tmp_path))
    assert passed.returncode == 0 and "match the manifest (sha256)" in passed.stdout, passed.stderr
    changed = tmp_path / "VGGT-1B" / "model.safetensors"
    data = bytearray(changed.read_bytes())
    data[3] ^= 1  # same size: only the hash can tell
    changed.write_bytes(bytes(data))
    assert tracegs_weights("--check", "--sizes-only", "--weights-dir", str(tmp_path)).returncode == 0
    failed = tracegs_weights("--check", "--weights-dir", str(tmp_path))
    assert failed.returncode == 2
    assert failed.stderr.strip().splitlines() == [
        f"tracegs-weights: error: {changed}: SHA-256 differs from the manifest's; fetch again (tracegs-weights)"]


@pytest.mark.parametrize("damage", ["missing", "truncated"])
def test_check_names_a_missing_or_resized_file(tmp_path, damage):
    fake_tree(tmp_path)
    assert tracegs_weights("--record", "--weights-dir", str(tmp_path)).returncode == 0
    damaged = tmp_path / "CogVideoX-5b-I2V" / "vae" / "diffusion_pytorch_model.safetensors"
    damaged.unlink() if damage == "missing" else damaged.write_bytes(b"x")
    failed = tracegs_weights("--check", "--weights-dir", str(tmp_path))
    assert failed.returncode == 2 and len(failed.stderr.strip().splitlines()) == 1
    assert str(damaged) in failed.stderr and ("missing" if damage == "missing" else "1 bytes") in failed.stderr


def test_record_refuses_a_tree_without_a_declared_file(tmp_path):
    fake_tree(tmp_path)
    (tmp_path / "VGGT-1B" / "config.json").unlink()
    run = tracegs_weights("--record", "--weights-dir", str(tmp_path))
    assert run.returncode == 2 and str(tmp_path / "VGGT-1B" / "config.json") in run.stderr
    assert not (tmp_path / MANIFEST).exists()  # nothing half-written
