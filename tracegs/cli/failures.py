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
    (:func:`tracegs.errors.out_of_memory`): the step that ran out (the innermost function of this package that was
    running, and the module being imported), what failed, and the address-space limit where one is set.

    A library under a memory limit tends to say something else: pycolmap, whose C++ module could not be mapped,
    asks to reinstall the package; the words here send the user to the memory instead."""
    memory = out_of_memory(error)
    step = next((f"{frame.f_globals.get('__name__')}.{frame.f_code.co_qualname}"
                 for frame, _ in reversed(list(traceback.walk_tb(error.__traceback__)))
                 if PACKAGE in Path(frame.f_code.co_filename).resolve().parents
                 and not str(frame.f_globals.get("__name__", "")).startswith("tracegs.cli")), "start-up")
    importing = next((f"importing {e.name}: " for e in (memory, memory.__context__) if isinstance(e, ImportError)
                      and e.name), "")
    limit, _ = resource.getrlimit(resource.RLIMIT_AS)
    under = "" if limit == resource.RLIM_INFINITY else f" under the address-space limit of {limit / 2**30:.2f} GiB " \
                                                        "(ulimit -v)"
    return OutOfMemoryError(step, f"out of memory ({importing}{one_line(memory, 200) or type(memory).__name__})"
                                  f"{under}", "free memory or raise the limit, then run the same command again "
                                              "(finished products are kept)")


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
