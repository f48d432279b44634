"""Where the frozen and trained networks run: one rule for every task."""

from __future__ import annotations

import torch


def accelerator() -> str:
    """``"cuda"`` when a GPU is visible, else ``"cpu"``: deployment, prepare and captioning all follow it."""
    return "cuda" if torch.cuda.is_available() else "cpu"
