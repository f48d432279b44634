"""Hydra command-line overrides read as data: which key one sets, and whether it describes the command's dataset."""

from __future__ import annotations

import re


def override_key(override: str) -> str:
    """``+loss.lambda_ret=0.3`` -> ``loss.lambda_ret``; ``teacher=v12`` -> ``teacher``."""
    return override.split("=", 1)[0].lstrip("+~")


def describes_the_dataset(override: str) -> bool:
    """Whether a command-line override sets the ``data`` group or a key inside it: a setting of the command's own
    dataset, which a step or lookup on another dataset (``data=mipnerf360``) leaves out."""
    return re.split(r"[./]", override_key(override), maxsplit=1)[0] == "data"
