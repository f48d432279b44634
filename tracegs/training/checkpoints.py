"""Lightning checkpoints that are safe to resume from: refused before loading when damaged or unsafe,
confirmed on disk after every save, and written when a signal stops the run."""

from __future__ import annotations

import os
import pickle
import signal
import threading
from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.plugins.environments import SLURMEnvironment
from lightning.pytorch.utilities.exceptions import SIGTERMException

from tracegs.errors import InputFileError, OutputPathError, TraceGSError, one_line

# Keys of a checkpoint's hyper_parameters that Lightning's ``load_from_checkpoint`` imports and calls.
IMPORTED_HPARAM_KEYS = ("_instantiator", "_class_path")


def require_loadable_checkpoint(path: str | Path, field: str) -> dict:
    """Load ``path`` with ``weights_only=True`` (memory-mapped, so cheap) before Lightning does; return it.

    A truncated file or one that needs pickled code would otherwise fail inside Lightning with a
    traceback; a pickled one is refused here rather than executed.
    """
    fix = f"delete it to start this stage from scratch, or set {field} to another checkpoint"
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError as error:
        raise InputFileError(path, "holds Python objects that safe loading (weights_only) refuses: loading them "
                                   "could run arbitrary code", fix) from error
    except (RuntimeError, EOFError, OSError, ValueError) as error:
        first_sentence = one_line(error).split(". ")[0]
        raise InputFileError(path, f"not a loadable training checkpoint ({first_sentence})", fix) from error
    # Lightning's loader imports what these keys name (an "instantiator" and its class); this code writes neither.
    hyper_parameters = checkpoint.get("hyper_parameters") if isinstance(checkpoint, dict) else None
    named_code = sorted(k for k in IMPORTED_HPARAM_KEYS if isinstance(hyper_parameters, dict) and k in hyper_parameters)
    if named_code:
        raise InputFileError(path, f"its hyper_parameters name code to import ({', '.join(named_code)}): loading "
                                   "it could run arbitrary code", fix)
    return checkpoint


def requeue_checkpoints(run_dir: Path) -> list[Path]:
    """The ``hpc_ckpt_<n>.ckpt`` files Lightning's SLURM requeue handler wrote in ``run_dir`` (its
    ``default_root_dir``), in the order of ``n``."""
    return sorted(run_dir.glob("hpc_ckpt_*.ckpt"), key=lambda path: int(path.stem.rpartition("_")[2] or 0))


def keep_newest_requeue_checkpoint(run_dir: Path) -> None:
    """Delete every requeue checkpoint of ``run_dir`` but the newest (each is ~0.8 GB at paper scale and a Stage-2
    run is requeued several times); called once the newest is on disk."""
    for older in requeue_checkpoints(run_dir)[:-1]:
        older.unlink(missing_ok=True)


def newest_checkpoint(paths: list[Path], field: str) -> Path | None:
    """The existing file of ``paths`` with the highest ``global_step`` (the first of equals), each checked
    loadable; None when none exists."""
    newest, newest_step = None, -1
    for path in paths:
        if path.is_file():
            step = require_loadable_checkpoint(path, field).get("global_step", 0)
            if step > newest_step:
                newest, newest_step = path, step
    return newest


def finished_checkpoint_state(path: str | Path, max_steps: int) -> dict | None:
    """The weights to export from a checkpoint that already reached ``max_steps``, else None.

    Lightning resumed from such a checkpoint trains nothing and never calls the weight average's end-of-training
    hook, so the module would keep the raw last-step weights. The checkpoint's ``state_dict`` is what the first
    completion exported: the average where the stage averages (the callback stores the current weights beside
    it as ``current_model_state``), else the last step's weights.
    """
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    if max_steps < 0 or checkpoint.get("global_step", 0) < max_steps:
        return None
    return checkpoint


class ConfirmedCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` that checks each file it saved exists and also saves at the run's last step.

    Lightning's atomic save swallows a ``PermissionError`` (e.g. a read-only ``checkpoints/``), so
    without this a run finishes with exit code 0 and nothing to resume from. Saving only every n steps would
    leave the last steps out of ``last.ckpt`` when n does not divide ``max_steps``: a rerun would train them again.
    """

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if 0 < trainer.max_steps <= trainer.global_step and not self._should_skip_saving_checkpoint(trainer):
            candidates = self._monitor_candidates(trainer)
            self._save_topk_checkpoint(trainer, candidates)
            self._save_last_checkpoint(trainer, candidates)

    def _save_checkpoint(self, trainer, filepath: str) -> None:
        super()._save_checkpoint(trainer, filepath)
        if trainer.is_global_zero and not Path(filepath).is_file():
            raise OutputPathError(Path(filepath).parent, f"checkpoint {Path(filepath).name} was not written",
                                  "make the folder writable (or choose another run_dir) and rerun to resume")


class CheckpointOnSignal(Callback):
    """Write ``last.ckpt`` after the current step and stop when SIGTERM (or SIGUSR2) arrives; under SLURM, run
    Lightning's requeue after the current step.

    Lightning's signal connector records SIGTERM in ``trainer.received_sigterm``, but a single process acts
    on it only at the end of an epoch, which at paper scale is hours away. This callback makes it act after
    the step in flight, through Lightning's own ``save_checkpoint`` and ``SIGTERMException``. Outside SLURM
    the requeue signal (SIGUSR2, the signal the SLURM scripts ask for before a time limit) is forwarded as
    SIGTERM. Under SLURM Lightning's ``SLURMEnvironment`` owns it: its handler saves ``hpc_ckpt_<n>.ckpt`` and
    calls ``scontrol requeue``. Lightning runs that handler the moment the signal lands, which can be between
    the optimizer's update and the step counter's increment, or inside another checkpoint's save: a
    checkpoint that a resumed run would replay a step on top of. So the handler is kept and run here, after
    the step in flight, like the SIGTERM checkpoint; every rank runs it when any rank received the signal, as
    its save is a collective.
    """

    def __init__(self, last_checkpoint: Path, requeue_signal: int | None = getattr(signal, "SIGUSR2", None)) -> None:
        self.last_checkpoint = last_checkpoint
        self.requeue_signal = requeue_signal
        self.slurm_requeue = None  # Lightning's requeue handler, once deferred
        self.requeue_requested = False

    def setup(self, trainer, pl_module, stage: str) -> None:
        if not SLURMEnvironment.detect() and self.requeue_signal is not None:
            signal.signal(self.requeue_signal, lambda *_: os.kill(os.getpid(), signal.SIGTERM))

    def on_train_start(self, trainer, *_) -> None:
        # Lightning registers its handlers after the setup hooks and before this one; its teardown restores
        # the handler it found, so the deferral ends with the fit.
        handler = signal.getsignal(self.requeue_signal) if self.requeue_signal is not None else None
        if SLURMEnvironment.detect() and callable(handler) and threading.current_thread() is threading.main_thread():
            self.slurm_requeue, self.requeue_requested = handler, False
            signal.signal(self.requeue_signal, self._request_requeue)

    def _request_requeue(self, *_) -> None:
        self.requeue_requested = True

    def on_train_batch_end(self, trainer, *_) -> None:
        if self.slurm_requeue is not None and trainer.strategy.reduce_boolean_decision(self.requeue_requested,
                                                                                       all=False):
            self.requeue_requested = False
            self.slurm_requeue(self.requeue_signal, None)  # saves hpc_ckpt_<n+1>.ckpt, then requeues
            if trainer.is_global_zero:
                keep_newest_requeue_checkpoint(Path(trainer.default_root_dir))
        if trainer.received_sigterm:
            trainer.save_checkpoint(self.last_checkpoint)
            raise SIGTERMException()


def stopped_by_signal(last_checkpoint: Path, step: int) -> TraceGSError:
    """The one-line report of a run that a signal stopped after writing its checkpoint."""
    return TraceGSError(last_checkpoint, f"training stopped by a signal after step {step}; this checkpoint "
                        "holds it", "rerun the same command to resume")
