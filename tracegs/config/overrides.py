"""Hydra command-line overrides read as data: which key one sets, and whether it describes the command's dataset."""

from __future__ import annotations

import re
from collections.abc import Sequence


def override_key(override: str) -> str:
    """``+loss.lambda_ret=0.3`` -> ``loss.lambda_ret``; ``teacher=v12`` -> ``teacher``."""
    return override.split("=", 1)[0].lstrip("+~")


def describes_the_dataset(override: str) -> bool:
    """Whether a command-line override sets the ``data`` group or a key inside it: a setting of the command's own
    dataset, which a step or lookup on another dataset (``data=mipnerf360``) leaves out."""
    return re.split(r"[./]", override_key(override), maxsplit=1)[0] == "data"


def with_overrides(base: Sequence[str], winning: Sequence[str]) -> list[str]:
    """``base`` without the overrides of keys that ``winning`` sets, then ``winning``: its values win."""
    replaced = {override_key(o) for o in winning}
    return [o for o in base if override_key(o) not in replaced] + list(winning)
