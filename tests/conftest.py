"""Project-wide test settings.

Every test runs with one intra-op thread: the tensors are tiny, and on a shared 2-core machine spinning
OpenMP workers made the suite 5-20x slower (measured by the package helpers). The setting is session-wide
and autouse, so it is in force before any session fixture (e.g. the prepared cache) is built.
"""

import contextlib
import dataclasses
import importlib
import multiprocessing
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hydra import initialize_config_dir

from tracegs.config.schema import register_configs
from tracegs.location import CONF_DIR
from tracegs.pipeline.runner import composed
from tracegs.training.strategy import LAUNCH_ENV


@pytest.fixture(autouse=True, scope="session")
def single_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(autouse=True)
def process_state_left_as_found():
    """Every test leaves this process's distributed state as it found it: the later tests fork demos and start
    worker pools from this process. A leak fails the test that left it (and is undone for the ones after)."""
    excepthook, launch_env = sys.excepthook, {key: os.environ.get(key) for key in LAUNCH_ENV}
    yield
    leaked = []
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
        leaked.append("a process group")
    if sys.excepthook is not excepthook:
        sys.excepthook = excepthook
        leaked.append("sys.excepthook (init_process_group's rank prefix)")
    for key, value in launch_env.items():
        if os.environ.get(key) != value:
            leaked.append(f"${key}")
            if value is None:
                os.environ.pop(key)
            else:
                os.environ[key] = value
    assert not leaked, f"the test left {', '.join(leaked)} behind in the pytest process"


@pytest.fixture(scope="module")
def hydra_context():
    """Hydra initialised on the package's config tree, for a module's ``compose`` calls."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        yield


@pytest.fixture
def entry_config():
    """Compose as an entry point does (tracegs.pipeline.runner.composed): the config keeps the overrides it was
    given as its ``command_line``, from which an in-process runner composes its steps."""
    return composed


@dataclasses.dataclass
class EntryPointRun:
    returncode: int
    stdout: str
    stderr: str

    def stderr_lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.strip()]


def fork_child(work: Callable[[], None], stdout: Path, stderr: Path) -> multiprocessing.process.BaseProcess:
    """Start ``work()`` in a forked child of this process with stdout / stderr going to the given files; returns
    the started process (``join()`` it, then read ``exitcode``). The child exits 0 when ``work`` returns, with its
    ``SystemExit`` code, else 1 (traceback on its stderr); it never returns into pytest.

    Forking skips the ~7 s of imports a fresh interpreter would spend, and the child runs the real code with
    real file descriptors and exit code. The fork is multiprocessing's, not a bare ``os.fork``: it runs the
    after-fork hooks, so the child gets its own resource sharer (a bare fork inherits pytest's, whose socket
    then answers the child's worker processes for file descriptors it never registered: a broken pool).
    """

    def child() -> None:
        for fd, path in ((1, stdout), (2, stderr)):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
        sys.stdout = open(1, "w", buffering=1, closefd=False)
        sys.stderr = open(2, "w", buffering=1, closefd=False)
        work()

    process = multiprocessing.get_context("fork").Process(target=child)
    process.start()
    return process


@pytest.fixture
def forked():
    return fork_child


def run_entry_point(app: str, args: list[str], cwd: Path, in_child: Callable[[], None] | None = None
                    ) -> EntryPointRun:
    """Run console script ``tracegs-<app>`` (its Hydra main) with ``args`` in a forked child of this process;
    ``in_child`` runs in the child first (e.g. to set a resource limit on it alone)."""
    out, err = cwd / f".{app}.stdout", cwd / f".{app}.stderr"

    def main() -> None:
        if in_child is not None:
            in_child()
        os.chdir(cwd)
        for variable in ("TRACEGS_TRACEBACK", "HYDRA_FULL_ERROR"):
            os.environ.pop(variable, None)
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()
        sys.argv = [f"tracegs-{app}", *args]
        importlib.import_module(f"tracegs.cli.{app}").main()

    process = fork_child(main, out, err)
    process.join()
    run = EntryPointRun(process.exitcode, out.read_text(), err.read_text())
    out.unlink()
    err.unlink()
    return run


@pytest.fixture(scope="session")  # a plain function: module fixtures may use it too
def entry_point():
    return run_entry_point


@contextlib.contextmanager
def read_only_folder(path: Path):
    """Make ``path`` unwritable for this process: permission bits, or the immutable attribute for root (who
    ignores the bits); skips the test when neither is possible here."""
    if os.geteuid() != 0:
        path.chmod(0o555)
        try:
            yield path
        finally:
            path.chmod(0o755)
        return
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)]).returncode != 0:
        pytest.skip("cannot make a folder read-only for root here (no chattr +i)")
    try:
        yield path
    finally:
        subprocess.run(["chattr", "-i", str(path)], check=True)


@pytest.fixture
def read_only():
    return read_only_folder
