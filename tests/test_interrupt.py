"""Ctrl-C through a real console script: the terminal sends SIGINT to the whole process group (the command and
its worker processes); the command stops within seconds with one line and the shell's code for SIGINT, leaves no
worker behind and no half-written product, and the same command then goes on to the bytes an uninterrupted run
makes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

# A's pretraining scenes: 3DGS fits in two workers, and no pretrained restorer needed before them (the training
# scenes' pseudo-targets come from A).
PREPARE = [str(Path(sys.executable).parent / "tracegs-prepare"), "data.prepare.workers=2", "data.prepare.split=pretrain"]


def start_in_own_group(args: list[str], root: Path) -> subprocess.Popen:
    """``args`` as a terminal's foreground job: its own process group, SIGINT at its default action."""
    env = {k: v for k, v in os.environ.items() if k not in ("TRACEGS_TRACEBACK", "HYDRA_FULL_ERROR")}
    return subprocess.Popen([*args, f"paths.root_dir={root}"], cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def living_members(pgid: int) -> list[int]:
    """The processes of group ``pgid`` still running (a zombie has ended; whether it is reaped is init's job)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, pgrp, ...
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


@pytest.mark.slow
def test_ctrl_c_during_the_fits_stops_in_one_line_with_code_130(tmp_path):
    process = start_in_own_group(PREPARE, tmp_path)
    deadline = time.monotonic() + 300
    for line in process.stdout:  # the worker processes are fitting once this line shows
        if "3DGS fits" in line or time.monotonic() > deadline:
            break
    time.sleep(2)
    os.killpg(process.pid, signal.SIGINT)
    stopped = time.monotonic()
    _, stderr = process.communicate(timeout=60)
    assert time.monotonic() - stopped <= 5
    assert process.returncode == 130, stderr[-3000:]
    assert stderr.strip().splitlines() == [
        "tracegs-prepare: error: interrupted (Ctrl-C); the same command goes on from the last finished product"]
    time.sleep(1)
    assert living_members(process.pid) == []  # no worker outlived the command
    assert not list((tmp_path / "data" / "cache").glob("*/manifest.json"))  # the cache is not declared finished

    finish(tmp_path)
    whole = tmp_path / "uninterrupted"
    whole.mkdir()
    finish(whole)
    assert data_files(tmp_path) == data_files(whole)


def finish(root: Path) -> None:
    """The prepare command run to its end on ``root``."""
    process = start_in_own_group(PREPARE, root)
    _, stderr = process.communicate(timeout=900)
    assert process.returncode == 0, stderr[-3000:]


def data_files(root: Path) -> dict[str, bytes]:
    """The bytes of every product under ``root/data`` (the scenes, the fits and the cache), by relative path; a
    temporary of ``atomic_write`` left by the interrupted run would show here."""
    data = root / "data"
    return {path.relative_to(data).as_posix(): path.read_bytes() for path in sorted(data.rglob("*")) if path.is_file()}
