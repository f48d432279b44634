"""What a console script does with an error the user can fix: one line on stderr (and in the run's log files),
exit code 2; the errors that count as the user's."""

from __future__ import annotations

import logging
import sys

from omegaconf import DictConfig, OmegaConf

from tracegs.console import to_log_files
from tracegs.errors import TraceGSError, one_line, write_failure

# Errors caused by the user's input (config values, files on disk): reported in one line, no traceback.
USER_ERRORS = (TraceGSError, ValueError, FileNotFoundError, NotADirectoryError, KeyError)


def user_error(error: BaseException, cfg: DictConfig) -> BaseException | None:
    """``error`` as the user should see it: itself when the user's input caused it, the one-line
    :func:`write_failure` when the machine refused a write that no writer of ours named, else None (a bug:
    the traceback is the useful report)."""
    if isinstance(error, OSError) and not isinstance(error, USER_ERRORS):
        # Library writers (Lightning's checkpoints, Hydra's logs) may leave the file unnamed; the run folder is.
        where = error.filename or f"a file in the run folder {OmegaConf.select(cfg, 'run_dir', default='.')}"
        return write_failure(where, error)
    return error


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
