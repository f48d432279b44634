"""Local-directory checks shared by every pretrained component (no network: weights must already be on disk)."""

from __future__ import annotations

from pathlib import Path


class MissingPretrainedError(FileNotFoundError):
    """A config field names a pretrained directory that does not exist."""


class MissingPackageError(MissingPretrainedError):
    """A pretrained component needs a package that is not installed (reported in one line, like a missing
    directory: the user fixes both by installing)."""


def require_local_dir(path: str | None, field: str) -> Path:
    """Return ``path`` as a directory Path, or raise a one-line error naming the config ``field``."""
    if not path:
        raise MissingPretrainedError(f"{field} is not set: point it at a local pretrained directory")
    directory = Path(path).expanduser()
    if not directory.is_dir():
        raise MissingPretrainedError(f"{field}={path!r} is not a directory")
    return directory
