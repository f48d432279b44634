"""Where the Hydra config tree is: every layer that reads a file from it (the CLI, the scene lists) asks here.

On the ground floor: it imports nothing of the project, so any package may ask it without an import cycle."""

from __future__ import annotations

import importlib.resources
import os

# The repository's conf/ folder, installed as the package tracegs.conf (pyproject.toml maps it), so an
# editable install and a wheel resolve it alike; TRACEGS_CONF points at another config tree if needed.
CONF_DIR = os.environ.get("TRACEGS_CONF") or str(importlib.resources.files("tracegs.conf"))  # the package only when unset
