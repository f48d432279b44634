"""Where the frozen and trained networks run: one rule for every task."""

from __future__ import annotations

import torch


def accelerator() -> str:
    """``"cuda"`` when a GPU is visible, else ``"cpu"``: deployment, prepare and captioning all follow it."""
    return "cuda" if torch.cuda.is_available() else "cpu"


# Lightning's accelerator names that run on a CUDA device (``trainer.accelerator``; "auto" takes what is there).
CUDA_ACCELERATORS = ("gpu", "cuda")


def require_trainer_device(accelerator: str, field: str = "trainer.accelerator") -> None:
    """Refuse, before any work, a trainer set to run on a CUDA device where none is visible (``trainer=gpu`` on a
    CPU-only machine): Lightning would otherwise stop only when training starts, with its own traceback, after
    every step before it (the demo's preparation: minutes) had run."""
    if str(accelerator).lower() in CUDA_ACCELERATORS and not torch.cuda.is_available():
        from tracegs.errors import ConfigError

        cuda = f"torch {torch.__version__}, " + (f"built for CUDA {torch.version.cuda}" if torch.version.cuda
                                                 else "a CPU-only build")
        raise ConfigError(field, f"{accelerator!r} needs a CUDA device and this machine has none ({cuda}); "
                                 "run with trainer=cpu here")
