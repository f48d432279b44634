"""Products are written atomically and readable as the umask allows (shared file systems)."""

from __future__ import annotations

import json
import os
import stat

import pytest
from support.read_only import read_only_view

from tracegs.errors import OutputPathError
from tracegs.io import atomic_directory, save_safetensors_atomic, write_json_atomic


@pytest.fixture
def umask():
    previous = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(previous)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize(("mask", "file_mode", "dir_mode"), [(0o022, 0o644, 0o755), (0o002, 0o664, 0o775),
                                                              (0o077, 0o600, 0o700)])
def test_products_take_the_umask_permissions(tmp_path, umask, mask, file_mode, dir_mode):
    import torch

    umask(mask)
    write_json_atomic({"a": 1}, tmp_path / "results.json")
    save_safetensors_atomic({"w": torch.zeros(2)}, tmp_path / "adapter.safetensors")
    with atomic_directory(tmp_path / "model") as staging:
        (staging / "config.json").write_text("{}")
    assert mode(tmp_path / "results.json") == file_mode
    assert mode(tmp_path / "adapter.safetensors") == file_mode
    assert mode(tmp_path / "model") == dir_mode
    assert mode(tmp_path / "model" / "config.json") == file_mode


def test_a_file_made_again_with_the_same_bytes_is_left_untouched(tmp_path):
    """A rerun that writes a product again does not touch it (same inode, same modification time); other bytes
    replace it."""
    path = tmp_path / "results.json"
    write_json_atomic({"a": 1}, path)
    os.utime(path, ns=(1, 1))
    before = os.stat(path)
    write_json_atomic({"a": 1}, path)
    after = os.stat(path)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, 1)
    write_json_atomic({"a": 2}, path)
    assert json.loads(path.read_text()) == {"a": 2} and os.stat(path).st_ino != before.st_ino
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]  # no temporary left beside it


def test_a_read_only_copy_takes_the_same_bytes_and_refuses_others_in_one_line(tmp_path):
    """A finished product on a read-only file system: writing it again with the same bytes succeeds without a
    write; other bytes are refused naming the file, and nothing is left anywhere."""
    source = tmp_path / "root"
    source.mkdir()
    write_json_atomic({"a": 1}, source / "results.json")
    with read_only_view(source, tmp_path / "view") as view:
        write_json_atomic({"a": 1}, view / "results.json")
        with pytest.raises(OutputPathError, match=r"results\.json: cannot write \(Read-only file system\)"):
            write_json_atomic({"a": 2}, view / "results.json")
    assert json.loads((source / "results.json").read_text()) == {"a": 1}
    assert [p.name for p in source.iterdir()] == ["results.json"]
