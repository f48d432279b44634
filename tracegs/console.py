"""What a run shows the user (tables, where outputs landed, its error) also goes to the run's log files."""

from __future__ import annotations

import logging
import math
import sys
import time
import warnings
from pathlib import Path

log = logging.getLogger("tracegs")


def log_files() -> list[logging.FileHandler]:
    """The file handlers of the root logger (Hydra's job log)."""
    return [handler for handler in logging.getLogger().handlers if isinstance(handler, logging.FileHandler)]


class LogBookmark:
    """Where each log file of the run ends now, so that a run which made nothing can leave its logs as they were
    (a rerun of finished work keeps the record of the run that made it; its own lines went to the console)."""

    def __init__(self) -> None:
        self.lengths = {Path(h.baseFilename): Path(h.baseFilename).stat().st_size
                        for h in log_files() if Path(h.baseFilename).is_file()}

    def kept(self) -> bool:
        """Whether every log file is as long as at the bookmark (rewound, or nothing logged since)."""
        return all(path.is_file() and path.stat().st_size == length for path, length in self.lengths.items())

    def rewind(self) -> None:
        """Cut each log file back to its length at the bookmark (handlers append, so they go on from there)."""
        for handler in log_files():
            handler.flush()
        for path, length in self.lengths.items():
            with path.open("r+b") as file:
                file.truncate(length)


def to_log_files(text: str, level: int = logging.INFO) -> None:
    """Write ``text`` to every file handler of the root logger (Hydra's job log), not to the console."""
    for handler in log_files():
        handler.emit(log.makeRecord(log.name, level, __file__, 0, text, None, None))


def show(text: str = "") -> None:
    """Print ``text`` on stdout as is (tables stay copy-pasteable) and keep it in the log files."""
    print(text)
    sys.stdout.flush()
    to_log_files(text)


# Library notices that say nothing a user of this project can act on, each with why it is safe to drop. Every
# other warning still shows (a Lightning hint about the user's own settings, the project's own warnings).
KNOWN_WARNINGS = (
    # Validation runs as callbacks on the deployed restorer (tracegs/eval/callback.py), never as a Lightning val
    # loop: the DataModule's ``val_dataloader`` serves those scenes, and the Trainer's loop is off by design.
    ("You passed in a `val_dataloader` but have no `validation_step`", UserWarning),
    # Lightning's own use of a torch class that torch deprecates: fixed by a Lightning release, not by a user.
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),
    # Manual-optimisation checkpoints hold the weights after the step, which is what exact resume needs: the
    # checkpoint of step k is the state step k + 1 starts from (Lightning adds a page of example code).
    ("Using ModelCheckpoint with manual optimization", UserWarning),
    # The weight average copies the module after ``configure_model``; only a sharded run would make that a copy
    # of a shard, and the baseline (the one stage that averages) never shards.
    ("You're using the WeightAveraging callback with a model that overrides", UserWarning),
)
# Lightning's advertisements for its other products (litlogger, litmodels), logged at INFO by its rank-zero
# logger on every Trainer.
ADVERTISEMENT = "\N{ELECTRIC LIGHT BULB} Tip:"
LIGHTNING_NOTICES = "lightning.pytorch.utilities.rank_zero"


class _DropAdvertisements(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(ADVERTISEMENT)


def quiet_library_notices() -> None:
    """Drop the library notices above from the console and the log files (idempotent: an entry point calls it
    before the libraries speak; a filter added twice replaces the first)."""
    for message, category in KNOWN_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)
    logger = logging.getLogger(LIGHTNING_NOTICES)
    if not any(isinstance(f, _DropAdvertisements) for f in logger.filters):
        logger.addFilter(_DropAdvertisements())


# A plain-text progress line at most this often: a progress bar's redraws are unreadable in log files and
# SLURM output, and one line every half minute keeps a long job visibly alive without flooding its log.
PROGRESS_EVERY_S = 30.0


def interactive() -> bool:
    """Whether stdout is a terminal (progress bars) rather than a file or pipe (plain progress lines)."""
    return sys.stdout.isatty()


def seconds_left(done: int, total: int, elapsed: float, parallel: int = 1) -> float:
    """Time left from the measured throughput: ``parallel`` items run at once, each taking ``elapsed * parallel /
    done`` on average, so the ``total - done`` left take that many rounds of ``parallel`` (the last round may be
    partly idle). One at a time this is ``elapsed / done`` per item left."""
    if not done:
        return float("nan")
    return math.ceil((total - done) / parallel) * elapsed * parallel / done


class PlainProgress:
    """Logs ``<label>: <done>/<total>, <elapsed> s, ~<left> s left`` at most every ``PROGRESS_EVERY_S`` and at
    the end, when stdout is not a terminal (the log file gets the lines either way); ``parallel`` items run at
    once (:func:`seconds_left`)."""

    def __init__(self, label: str, total: int, every_s: float = PROGRESS_EVERY_S, parallel: int = 1,
                 first: int = 0) -> None:
        # ``first``: items already done before this start (a resumed run), which took none of its time.
        self.label, self.total, self.every_s, self.parallel, self.first = label, total, every_s, parallel, first
        self.enabled = not interactive()
        self.start = self.last = time.monotonic()

    def update(self, done: int, detail: str = "") -> None:
        now = time.monotonic()
        if not self.enabled or (now - self.last < self.every_s and done < self.total):
            return
        self.last = now
        elapsed = now - self.start
        left = seconds_left(done - self.first, self.total - self.first, elapsed, self.parallel)
        log.info("%s: %d/%d%s, %.0f s, ~%.0f s left", self.label, done, self.total, detail, elapsed, left)
