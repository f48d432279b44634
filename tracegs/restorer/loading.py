"""Local-directory checks shared by every pretrained component (no network: weights must already be on disk)."""

from __future__ import annotations

from pathlib import Path

import torch


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


def torch_dtype(name: str, field: str) -> torch.dtype:
    """The torch dtype a config field names ("float32", "bfloat16", ...), or a one-line error naming the field."""
    dtype = getattr(torch, name, None)
    if not isinstance(dtype, torch.dtype):
        raise ValueError(f"{field}={name!r} is not a torch dtype name")
    return dtype
