"""What a console script does with an error the user can fix: one line on stderr (and in the run's log files),
exit code 2; the errors that count as the user's."""

from __future__ import annotations

import logging
import resource
import sys
import traceback
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from tracegs.console import to_log_files
from tracegs.errors import TraceGSError, one_line, out_of_memory, write_failure

PACKAGE = Path(__file__).resolve().parents[1]

# Errors caused by the user's input (config values, files on disk): reported in one line, no traceback.
USER_ERRORS = (TraceGSError, ValueError, FileNotFoundError, NotADirectoryError, KeyError)


class OutOfMemoryError(TraceGSError):
    """An allocation, or the mapping of a shared library, failed: the machine's memory or the process's
    address-space limit (``ulimit -v``) ran out in the step named."""


def user_error(error: BaseException, cfg: DictConfig) -> BaseException | None:
    """``error`` as the user should see it: :func:`memory_failure` when memory ran out, itself when the user's input
    caused it, the one-line :func:`write_failure` when the machine refused a write that no writer of ours named,
    else None (a bug: the traceback is the useful report)."""
    if out_of_memory(error) is not None:
        return memory_failure(error)
    if not isinstance(error, (*USER_ERRORS, OSError)):
        return None
    if isinstance(error, OSError) and not isinstance(error, USER_ERRORS):
        # Library writers (Lightning's checkpoints, Hydra's logs) may leave the file unnamed; the run folder is.
        where = error.filename or f"a file in the run folder {OmegaConf.select(cfg, 'run_dir', default='.')}"
        return write_failure(where, error)
    return error


def memory_failure(error: BaseException) -> OutOfMemoryError:
    """The one-line error for ``error``, in whose chain an allocation or a library's mapping failed
    (:func:`tracegs.errors.out_of_memory`): the step that ran out (:func:`_step`), what failed, and the
    address-space limit where one is set.

    A library under a memory limit tends to say something else: pycolmap, whose C++ module could not be mapped,
    asks to reinstall the package; the words here send the user to the memory instead."""
    memory = out_of_memory(error)
    importing = "importing " if any(isinstance(e, ImportError) for e in (memory, memory.__context__)) else ""
    limit, _ = resource.getrlimit(resource.RLIMIT_AS)
    under = "" if limit == resource.RLIM_INFINITY else f" under the address-space limit of {limit / 2**30:.2f} GiB " \
                                                        "(ulimit -v)"
    return OutOfMemoryError(_step(error), f"out of memory ({importing}{one_line(memory, 200) or 'MemoryError'})"
                                          f"{under}", "free memory or raise the limit, then run the same command "
                                                      "again (finished products are kept)")


def _step(error: BaseException) -> str:
    """Where ``error`` rose, as ``module.function``: the innermost function of this package outside the entry-point
    wrapper (the step that ran), else the library function the wrapper called (Hydra composing the config)."""
    frames = [(str(frame.f_globals.get("__name__")), frame.f_code.co_qualname.split(".<locals>.")[-1],
               PACKAGE in Path(frame.f_code.co_filename).resolve().parents)
              for frame, _ in traceback.walk_tb(error.__traceback__)]
    ours = [f"{module}.{name}" for module, name, inside in frames if inside and not module.startswith("tracegs.cli")]
    if ours:
        return ours[-1]
    called = [f"{module}.{name}" for (_, _, caller), (module, name, inside) in zip(frames, frames[1:])
              if caller and not inside]
    return called[-1] if called else "start-up"


def report_one_line(app: str, error: BaseException | str) -> str:
    """Print ``error`` as one line on stderr (and into the run's log files); return its message."""
    message = one_line(error.args[0] if isinstance(error, KeyError) and error.args else error, limit=2000)
    line = f"tracegs-{app}: error: {message}"
    to_log_files(line, logging.ERROR)  # not through the console handler: stderr gets the line exactly once
    print(line, file=sys.stderr)
    return message


def exit_with_one_line(app: str, error: BaseException) -> None:
    """The one line of :func:`report_one_line`, then exit code 2."""
    report_one_line(app, error)
    sys.exit(2)
