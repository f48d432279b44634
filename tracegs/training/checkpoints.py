"""Lightning checkpoints that are safe to resume from: refused before loading when damaged or unsafe,
and confirmed on disk after every save."""

from __future__ import annotations

import pickle
from pathlib import Path

import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from tracegs.errors import InputFileError, OutputPathError, one_line


def require_loadable_checkpoint(path: str | Path, field: str) -> None:
    """Load ``path`` with ``weights_only=True`` (memory-mapped, so cheap) before Lightning does.

    A truncated file or one that needs pickled code would otherwise fail inside Lightning with a
    traceback; a pickled one is refused here rather than executed.
    """
    try:
        torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as error:
        raise InputFileError(
            path, f"not a loadable training checkpoint ({one_line(error, limit=160)})",
            f"delete it to start this stage from scratch, or set {field} to another checkpoint",
        ) from error


class ConfirmedCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` that checks each file it saved exists.

    Lightning's atomic save swallows a ``PermissionError`` (e.g. a read-only ``checkpoints/``), so
    without this a run finishes with exit code 0 and nothing to resume from.
    """

    def _save_checkpoint(self, trainer, filepath: str) -> None:
        super()._save_checkpoint(trainer, filepath)
        if trainer.is_global_zero and not Path(filepath).is_file():
            raise OutputPathError(Path(filepath).parent, f"checkpoint {Path(filepath).name} was not written",
                                  "make the folder writable (or choose another run_dir) and rerun to resume")
