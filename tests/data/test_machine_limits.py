"""What a machine may lack, through the real entry point: a writable home folder (the compiled rasterizer is built
elsewhere and changes no byte), a C++ compiler (``auto`` is refused in one line, ``torch`` asked for gets its own
folder) and memory (one line naming memory and the step, exit 2, no run folder left)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hydra import compose
from scene_builders import write_scene
from support.inputs import TINY_PREPARE, assert_refused, files_under

from tracegs.splat import rasterize_compiled


def tiny_prepare(root: Path) -> list[str]:
    """A one-scene tiny prepare under ``root`` (its scene written there first)."""
    write_scene(root / "scenes" / "ring", n=12)
    return [*TINY_PREPARE, f"data.source.root={root / 'scenes'}", f"paths.root_dir={root}"]


def written(root: Path) -> set[Path]:
    return files_under(root) - files_under(root / "scenes")


def products(root: Path) -> dict[str, bytes]:
    """Every file of the caches under ``root`` (their lock files aside) by path inside the cache folder."""
    cache = root / "data" / "cache"
    return {str(path.relative_to(cache)): path.read_bytes() for path in files_under(cache) if path.name != ".tracegs.lock"}


def fresh_build(environment: dict[str, str | None]):
    """In the child: ``environment`` applied (None removes a variable), and the compiled library forgotten, so the
    child looks for and builds it as a new process would (the parent may have loaded it)."""

    def apply() -> None:
        for key, value in environment.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        tempfile.tempdir = None  # read $TMPDIR again
        rasterize_compiled.library.cache_clear()
        rasterize_compiled.compiled_unavailable.cache_clear()

    return apply


@pytest.mark.slow  # two tiny prepares and a fresh build of the library: ~40 s on 2 cores
def test_an_unwritable_home_builds_the_rasterizer_in_the_temporary_folder_and_changes_no_byte(
        tmp_path, entry_point, read_only):
    normal, homeless = tmp_path / "normal", tmp_path / "homeless"
    run = entry_point("prepare", tiny_prepare(normal), normal.parent)
    assert run.returncode == 0, run.stderr[-3000:]
    home, temporary = tmp_path / "home", tmp_path / "tmp"
    home.mkdir()
    temporary.mkdir()
    with read_only(home):
        run = entry_point("prepare", tiny_prepare(homeless), homeless.parent, fresh_build(
            {"HOME": str(home), "XDG_CACHE_HOME": None, "TORCH_EXTENSIONS_DIR": None, "TMPDIR": str(temporary)}))
    assert run.returncode == 0, run.stderr[-3000:]
    built_in = temporary / f"tracegs-torch-extensions-{os.getuid()}"
    said = [line for line in run.stdout.splitlines() if "building the compiled rasterizer in" in line]
    assert len(said) == 1 and f"torch extensions cache {home / '.cache' / 'torch_extensions'} not writable (" in said[0]
    assert said[0].endswith(f"): building the compiled rasterizer in {built_in}"), said
    assert list(built_in.glob("tracegs_rasterize_*/*.so")), "the library was not built in the temporary folder"
    assert (built_in.stat().st_mode & 0o777) == 0o700  # a private folder: others cannot plant a library there
    assert products(homeless) == products(normal) and products(normal)


def test_without_a_compiler_auto_is_refused_in_one_line_and_torch_gets_its_own_folder(
        tmp_path, entry_point, hydra_context):
    args = tiny_prepare(tmp_path)
    run = entry_point("prepare", args, tmp_path, fresh_build(
        {"TORCH_EXTENSIONS_DIR": str(tmp_path / "extensions"), "CXX": str(tmp_path / "no-compiler" / "c++")}))
    assert_refused(run, "prepare", "config field 'data.prepare.fit.backend': 'auto' renders with the compiled CPU "
                                   "rasterizer, which cannot be built here (", written(tmp_path) - files_under(
                                       tmp_path / "extensions"))
    line = run.stderr_lines()[0]
    assert f"{tmp_path / 'no-compiler' / 'c++'}: not found" in line and "set data.prepare.fit.backend=torch" in line
    # The fix asked for names another cache than the one auto would have made, never the same folder.
    caches = {backend: compose(config_name="prepare", overrides=[*args, f"data.prepare.fit.backend={backend}"])
              .data.prepare.cache_dir for backend in ("auto", "torch")}
    assert caches["auto"] != caches["torch"]


MAPPED_AFTER_IMPORT = ("import tracegs.cli.prepare\n"
                       "print(next(line.split()[1] for line in open('/proc/self/status') if line.startswith('VmSize:')))")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the mapped size from /proc")
def test_running_out_of_memory_is_one_line_naming_memory_and_the_step(tmp_path):
    """A fresh interpreter (a forked child would reuse the memory its parent's earlier tests freed) limited, as
    ``ulimit -v`` would, to what the entry point's imports map plus 16 MiB: the run starts, then runs out."""
    # One OpenMP thread, as the test suite runs: libgomp ends the process itself (exit 1, its own words) when it
    # cannot map a thread's stack, which leaves nothing for the entry point to report.
    environment = {**{key: value for key, value in os.environ.items()
                      if key not in ("TRACEGS_TRACEBACK", "HYDRA_FULL_ERROR")}, "OMP_NUM_THREADS": "1"}
    mapped = int(subprocess.run([sys.executable, "-c", MAPPED_AFTER_IMPORT], capture_output=True, text=True,
                                env=environment, check=True).stdout) * 1024
    limit = mapped + 16 * 2**20

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))

    run = subprocess.run([sys.executable, "-m", "tracegs.cli.prepare", *tiny_prepare(tmp_path)], cwd=tmp_path,
                         env=environment, preexec_fn=limited, capture_output=True, text=True)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1, run.stderr[-3000:]
    line = lines[0]
    assert line.startswith("tracegs-prepare: error: ") and ": out of memory (" in line, line
    assert written(tmp_path) == set()
    step = line.removeprefix("tracegs-prepare: error: ").split(":")[0]
    assert step.startswith(("tracegs.", "hydra.")), line  # the step that ran out, as module.function
    assert f"under the address-space limit of {limit / 2**30:.2f} GiB (ulimit -v); free memory or raise" in line
    assert not (tmp_path / "outputs").exists(), "the run folder was left behind"
