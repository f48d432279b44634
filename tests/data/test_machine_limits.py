"""What a machine may lack, through the real entry point: a writable home folder (the compiled rasterizer is built
elsewhere and changes no byte), a C++ compiler (``auto`` is refused in one line, ``torch`` asked for gets its own
folder) and memory (one line naming memory and the step, exit 2, no run folder left)."""

from __future__ import annotations

import importlib
import os
import resource
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


def address_space_a_little_above_now() -> None:
    """Limit the child's address space to what it maps now plus 16 MiB, as ``ulimit -v`` would: too little to run
    the preparation. The entry point's module is imported first, as the console script does before any of the
    project's code runs (a library that cannot be mapped at that point fails before the entry point exists)."""
    importlib.import_module("tracegs.cli.prepare")
    with open("/proc/self/status") as status:
        mapped = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (mapped + 16 * 2**20, resource.getrlimit(resource.RLIMIT_AS)[1]))


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the mapped size from /proc")
def test_running_out_of_memory_is_one_line_naming_memory_and_the_step(tmp_path, entry_point):
    run = entry_point("prepare", tiny_prepare(tmp_path), tmp_path, address_space_a_little_above_now)
    assert_refused(run, "prepare", ": out of memory (", written(tmp_path))
    line = run.stderr_lines()[0]
    step = line.removeprefix("tracegs-prepare: error: ").split(":")[0]
    assert step.startswith(("tracegs.", "hydra.")), line  # the step that ran out, as module.function
    assert "GiB (ulimit -v); free memory or raise the limit" in line
    assert not (tmp_path / "outputs").exists(), "the run folder was left behind"
