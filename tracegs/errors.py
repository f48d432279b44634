"""The project's error type for problems a user can fix: a bad input file, an unwritable output, a
mismatch between a file and the config, a non-finite number.

Each error names where the problem is (a file or a dotted config field) and what to do about it. They
are raised at the boundary where the project reads or writes, and the entry-point wrapper
(``tracegs.cli.app``) prints them as one line on stderr with exit code 2.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


class ConfigError(ValueError):
    """An invalid config value or combination of values; ``field`` is the dotted key to change.

    A config dataclass that checks its own fields names them relative to itself; the composed config's
    validation (tracegs.config.validate) re-raises with the section prefixed (:meth:`under`).
    """

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"config field '{field}': {problem}")
        self.field, self.problem = field, problem

    def __reduce__(self):  # rebuilt from its fields when it crosses from a worker process
        return type(self), (self.field, self.problem)

    def under(self, section: str) -> ConfigError:
        """The same error for the field as seen from the root config, ``<section>.<field>``."""
        return ConfigError(f"{section}.{self.field}", self.problem)


class TraceGSError(Exception):
    """A user-fixable problem at ``where`` (a path or config field): ``"<where>: <problem>; <fix>"``."""

    def __init__(self, where: str | os.PathLike, problem: str, fix: str | None = None) -> None:
        self.where, self.problem, self.fix = str(where), problem, fix
        super().__init__(f"{self.where}: {problem}" + (f"; {fix}" if fix else ""))

    def __reduce__(self):  # rebuilt from its fields when it crosses from a worker process
        return type(self), (self.where, self.problem, self.fix)


class InputFileError(TraceGSError):
    """A file the run reads is missing, truncated, of the wrong format or unsafe to load."""


class OutputPathError(TraceGSError):
    """A folder the run writes to is not a writable directory, or a product did not appear on disk."""


class ConfigMismatchError(TraceGSError):
    """A file was written with settings that differ from the current config (both values named)."""


class NonFiniteError(TraceGSError):
    """A NaN or infinity where a finite number is required (a cached tensor, a loss, a metric)."""


def one_line(error: BaseException | str, limit: int = 300) -> str:
    """A library's error message squeezed onto one line (and cut at ``limit`` characters) for quoting."""
    text = " ".join(str(error).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def write_probe_failure(path: str | os.PathLike) -> tuple[Path, OSError | None]:
    """(the folder a file under ``path`` would be created in: ``path`` or its nearest existing parent, why a file
    cannot be created there or None). Nothing is left behind. A probe rather than permission bits, because those do
    not tell the whole story (read-only mounts, ACLs, root ignoring the bits)."""
    directory = Path(path)
    existing = next((p for p in (directory, *directory.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        return existing, None
    probe = existing / f".write-probe-{os.getpid()}"
    try:
        probe.touch()
        probe.unlink()
    except OSError as error:
        return existing, error
    return existing, None


def writable(path: str | os.PathLike) -> bool:
    """Whether a file can be created in ``path`` (or, when it does not exist yet, where it would be created)."""
    return write_probe_failure(path)[1] is None


def require_writable_dir(path: str | os.PathLike, field: str, finished_ok: bool = False) -> Path:
    """Check that ``path`` is, or can be created as, a writable directory; raise naming ``field`` otherwise.
    Nothing is created (:func:`write_probe_failure`). ``finished_ok``: an existing folder nothing can be written
    to passes (a read-only copy of a finished root): a step that finds its products finished writes nothing there,
    and one that would write refuses at its first write, naming the file."""
    existing, error = write_probe_failure(path)
    if not existing.is_dir():
        raise OutputPathError(existing, f"is a file, but {field} needs a directory here",
                              f"move the file away or choose another {field}")
    if error is not None and not (finished_ok and existing == Path(path)):
        raise OutputPathError(existing, f"not writable ({error.strerror or error})",
                              f"fix the folder's permissions or choose another {field}") from error
    return Path(path)


def plain_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be one path component under a root (a separator, ``..``, absolute, empty), or None.
    Scene, experiment and variant names become folder names: one that is not plain would read or write
    outside the folders the run was given."""
    if not name or name in (".", ".."):
        return "is empty, '.' or '..'"
    if "/" in name or "\\" in name or "\0" in name:
        return "holds a path separator"
    return None


def require_plain_name(name: str, field: str) -> str:
    """``name`` unchanged, or :class:`ConfigError` naming ``field`` when it is not a plain name."""
    problem = plain_name_problem(str(name))
    if problem:
        raise ConfigError(field, f"{name!r} {problem}; it becomes a folder name, so give a plain name "
                                 "(no '/', no '..', not absolute)")
    return name


# What to do when the machine refuses a write: the file system is full, the file exceeds a size limit, the
# file system is read-only, or the folder's permissions forbid it.
WRITE_FAILURES = {
    errno.ENOSPC: "free space on that file system (or set paths.root_dir elsewhere) and run the same command again",
    errno.EDQUOT: "free space within your quota (or set paths.root_dir elsewhere) and run the same command again",
    errno.EFBIG: "raise the file-size limit (ulimit -f) or write to a file system that allows larger files, then "
                 "run the same command again",
    errno.EROFS: "the file system is mounted read-only: set paths.root_dir (or the field naming this path) to a "
                 "writable folder",
    errno.EACCES: "fix the folder's permissions or set paths.root_dir (or the field naming this path) elsewhere",
    errno.EPERM: "fix the folder's permissions or set paths.root_dir (or the field naming this path) elsewhere",
}


def write_failure(path: str | os.PathLike, error: OSError) -> OutputPathError | None:
    """The one-line error for a write to ``path`` that the machine refused (:data:`WRITE_FAILURES`), else None.
    Products already finished are kept and nothing half-written is left, so the fix ends with a rerun."""
    if error.errno not in WRITE_FAILURES:
        return None
    return OutputPathError(path, f"cannot write ({error.strerror or os.strerror(error.errno)})",
                           WRITE_FAILURES[error.errno])


# How libraries say an allocation or a mapping failed: CPython's MemoryError aside, torch's CPU allocator ("can't
# allocate memory"), CUDA's ("out of memory"), and the dynamic loader, which maps a shared library's segments
# when it is imported ("failed to map segment from shared object", "cannot allocate memory"); a package may wrap
# that ImportError in its own "cannot import" error, so the whole chain is read.
_MEMORY_WORDS = ("failed to map segment", "cannot allocate memory", "can't allocate memory", "out of memory")


def out_of_memory(error: BaseException) -> BaseException | None:
    """The exception in ``error``'s chain (itself, its causes and contexts) that says an allocation or the mapping
    of a shared library failed, or None."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if (isinstance(error, MemoryError) or (isinstance(error, OSError) and error.errno == errno.ENOMEM)
                or any(words in str(error).lower() for words in _MEMORY_WORDS)):
            return error
        error = error.__cause__ or error.__context__
    return None
