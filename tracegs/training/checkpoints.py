"""Lightning checkpoints that are safe to resume from: refused before loading when damaged or unsafe,
confirmed on disk after every save, and written when a signal stops the run."""

from __future__ import annotations

import os
import pickle
import signal
from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.plugins.environments import SLURMEnvironment
from lightning.pytorch.utilities.exceptions import SIGTERMException

from tracegs.errors import InputFileError, OutputPathError, TraceGSError, one_line


def require_loadable_checkpoint(path: str | Path, field: str) -> None:
    """Load ``path`` with ``weights_only=True`` (memory-mapped, so cheap) before Lightning does.

    A truncated file or one that needs pickled code would otherwise fail inside Lightning with a
    traceback; a pickled one is refused here rather than executed.
    """
    fix = f"delete it to start this stage from scratch, or set {field} to another checkpoint"
    try:
        torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError as error:
        raise InputFileError(path, "holds Python objects that safe loading (weights_only) refuses: loading them "
                                   "could run arbitrary code", fix) from error
    except (RuntimeError, EOFError, OSError, ValueError) as error:
        first_sentence = one_line(error).split(". ")[0]
        raise InputFileError(path, f"not a loadable training checkpoint ({first_sentence})", fix) from error


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


class CheckpointOnSignal(Callback):
    """Write ``last.ckpt`` after the current step and stop when SIGTERM (or SIGUSR2) arrives.

    Lightning's signal connector records SIGTERM in ``trainer.received_sigterm``, but a single process acts
    on it only at the end of an epoch, which at paper scale is hours away. This callback makes it act after
    the step in flight, through Lightning's own ``save_checkpoint`` and ``SIGTERMException``. Outside SLURM
    SIGUSR2 (the signal the SLURM scripts ask for before a time limit) is forwarded as SIGTERM; under SLURM
    Lightning's ``SLURMEnvironment`` owns it (checkpoint and requeue).
    """

    def __init__(self, last_checkpoint: Path) -> None:
        self.last_checkpoint = last_checkpoint

    def setup(self, trainer, pl_module, stage: str) -> None:
        if not SLURMEnvironment.detect() and hasattr(signal, "SIGUSR2"):
            signal.signal(signal.SIGUSR2, lambda *_: os.kill(os.getpid(), signal.SIGTERM))

    def on_train_batch_end(self, trainer, *_) -> None:
        if trainer.received_sigterm:
            trainer.save_checkpoint(self.last_checkpoint)
            raise SIGTERMException()


def stopped_by_signal(last_checkpoint: Path, step: int) -> TraceGSError:
    """The one-line report of a run that a signal stopped after writing its checkpoint."""
    return TraceGSError(last_checkpoint, f"training stopped by a signal after step {step}; this checkpoint "
                        "holds it", "rerun the same command to resume")
