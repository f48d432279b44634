"""Writes the machine refuses, for real (a file-size limit, a full or read-only file system, a folder that
cannot be written): one line naming the file and what to do, exit code 2, nothing half-written."""

from __future__ import annotations

import contextlib
import resource
import subprocess
from pathlib import Path

import pytest
from safetensors import safe_open
from scene_builders import write_scene
from support.inputs import TINY_PREPARE

from tracegs.splat.ply import load_ply


@contextlib.contextmanager
def mounted_tmpfs(path: Path, options: str):
    """A tmpfs at ``path`` (root only; skips the test where mounting is not allowed)."""
    path.mkdir(parents=True, exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=True)


def file_size_limit() -> None:
    # Hydra's own records stay under it; the first 3DGS snapshot or shard does not.
    resource.setrlimit(resource.RLIMIT_FSIZE, (48 * 1024, resource.RLIM_INFINITY))


@pytest.mark.parametrize("fault", ["file_too_large", "disk_full", "read_only_file_system", "unwritable_folder"])
def test_a_refused_write_is_one_line_naming_the_file(tmp_path, entry_point, read_only, fault):
    scenes = tmp_path / "scenes"
    write_scene(scenes / "ring", n=12)
    cache = tmp_path / "cache"
    overrides = [*TINY_PREPARE, f"data.source.root={scenes}", f"data.prepare.cache_dir={cache}",
                 f"paths.root_dir={tmp_path}"]
    in_child, expected = None, ""
    with contextlib.ExitStack() as stack:
        if fault == "file_too_large":
            in_child, expected = file_size_limit, "cannot write (File too large); raise the file-size limit"
        elif fault == "disk_full":
            stack.enter_context(mounted_tmpfs(cache, "size=64k"))
            expected = "cannot write (No space left on device); free space"
        elif fault == "read_only_file_system":
            stack.enter_context(mounted_tmpfs(cache / "ring", "size=1m"))
            subprocess.run(["mount", "-o", "remount,ro", str(cache / "ring")], check=True)
            expected = "cannot write (Read-only file system); the file system"
        else:
            (cache / "ring").mkdir(parents=True)
            stack.enter_context(read_only(cache / "ring"))
            expected = "cannot write ("
        result = entry_point("prepare", overrides, tmp_path, in_child)
        lines = result.stderr_lines()
        assert result.returncode == 2, result.stderr[-3000:]
        assert len(lines) == 1 and lines[0].startswith("tracegs-prepare: error: "), result.stderr[-3000:]
        assert expected in lines[0], lines[0]
        if fault != "file_too_large":  # the first file of the scene's cache folder (a clip's, or its sheet)
            assert lines[0].startswith(f"tracegs-prepare: error: {cache / 'ring'}/"), lines[0]
        assert "fix the folder's permissions" in lines[0] or fault != "unwritable_folder"
        # Nothing half-written: no temporary left, and every product that exists is whole.
        assert [p for p in tmp_path.rglob("*.tmp")] == []
        for ply in tmp_path.rglob("*.ply"):
            assert len(load_ply(ply)) > 0
        for shard in tmp_path.rglob("*.safetensors"):
            with safe_open(str(shard), framework="pt") as handle:  # a truncated shard raises on opening or reading
                for key in handle.keys():
                    handle.get_tensor(key)
