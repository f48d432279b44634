"""Training progress as plain log lines when stdout is not a terminal (log files, SLURM output)."""

from __future__ import annotations

from lightning.pytorch.callbacks import Callback

from tracegs.console import PlainProgress


class PlainTrainingProgress(Callback):
    """Step, loss and time left at a fixed interval through :class:`tracegs.console.PlainProgress`."""

    progress: PlainProgress | None = None

    def on_train_start(self, trainer, pl_module) -> None:
        self.progress = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        # The clock starts with the first batch: what runs before it once (the held-out scoring of the initial
        # restorer, minutes at Stage 2's start) would otherwise be extrapolated over every step left. A resumed
        # run measures its time left on the steps it trains, not on those of the checkpoint.
        if self.progress is None:
            self.progress = PlainProgress("train", trainer.max_steps, first=trainer.global_step)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        loss = trainer.callback_metrics.get("loss")
        self.progress.update(trainer.global_step, f", loss {float(loss):.4g}" if loss is not None else "")
