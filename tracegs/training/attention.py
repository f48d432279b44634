"""The attention kernels of a fit's first training step, logged, and refused when unfused and a fused one is
required (``backbone.transformer.require_fused_attention``; tracegs.restorer.speed.AttentionKernels)."""

from __future__ import annotations

import logging

from lightning.pytorch.callbacks import Callback

from tracegs.restorer.speed import AttentionKernels

log = logging.getLogger(__name__)


class AttentionKernelCheck(Callback):
    """Records the SDPA kernel of every attention call of the first training step of a fit (every call of the
    step: the student's and the teacher's, with and without gradient) and logs them in one line; ``kernels``
    holds the counts afterwards. With ``require_fused``, the first unfused call stops the fit before it runs."""

    def __init__(self, require_fused: bool) -> None:
        self.require_fused = require_fused
        self.kernels: dict[str, int] | None = None
        self._recorder: AttentionKernels | None = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.kernels is None and self._recorder is None:
            self._recorder = AttentionKernels(self.require_fused)
            self._recorder.__enter__()  # a TorchFunctionMode sees the calls of the step that runs next

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self._recorder is not None:
            log.info(self._stop().summary())

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        if self._recorder is not None:  # a refused (or failed) first step leaves no mode behind
            self._stop()

    def _stop(self) -> AttentionKernels:
        recorder, self._recorder = self._recorder, None
        recorder.__exit__(None, None, None)
        self.kernels = dict(recorder.counts)
        return recorder
