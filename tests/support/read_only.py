"""A folder seen through a read-only bind mount: the file system refuses every write, also to root (whom
permission bits do not stop). Needs root with CAP_SYS_ADMIN; the tests that use it skip elsewhere."""

from __future__ import annotations

import contextlib
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def read_only_view(folder: Path, mount_point: Path) -> Iterator[Path]:
    """``folder`` mounted read-only at ``mount_point`` for the ``with`` block."""
    mount_point.mkdir(parents=True, exist_ok=True)
    bound = subprocess.run(["mount", "--bind", str(folder), str(mount_point)], capture_output=True, text=True)
    if bound.returncode != 0:
        pytest.skip(f"no read-only bind mount here: {bound.stderr.strip()}")
    try:
        subprocess.run(["mount", "-o", "remount,ro,bind", str(mount_point)], check=True, capture_output=True)
        yield mount_point
    finally:
        for _ in range(50):  # a process that just exited may hold it for a moment
            if subprocess.run(["umount", str(mount_point)], capture_output=True).returncode == 0:
                break
            time.sleep(0.1)
