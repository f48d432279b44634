"""The plain training progress line (log files, SLURM output) times the steps, not what ran once before them."""

from __future__ import annotations

import logging
import time

import lightning as L
import torch

from tracegs.training.progress import PlainTrainingProgress


class OneLayer(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch).pow(2).mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class SlowStart(L.Callback):
    """Stands for the held-out scoring of the initial restorer before Stage 2's first step."""

    def on_train_start(self, trainer, pl_module):
        time.sleep(1.5)


def test_time_before_the_first_step_is_not_counted(caplog, tmp_path):
    trainer = L.Trainer(max_steps=3, callbacks=[PlainTrainingProgress(), SlowStart()], logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, default_root_dir=tmp_path)
    with caplog.at_level(logging.INFO, logger="tracegs"):
        trainer.fit(OneLayer(), torch.utils.data.DataLoader(torch.ones(8, 2), batch_size=2))
    last = [r.getMessage() for r in caplog.records if r.getMessage().startswith("train: 3/3")]
    assert last == ["train: 3/3, 0 s, ~0 s left"]
