"""Where a number came from: the code's commit, the machine, the library versions.

Every table the demo writes carries this line, so a figure quoted elsewhere names the run behind it.
"""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import sys
from pathlib import Path


def git_commit() -> str:
    """The commit of the checkout this package runs from (``+dirty`` with local changes), or "unknown"."""
    root = Path(__file__).resolve().parents[1]
    # `git status` refreshes the index and takes .git/index.lock: a run must not block the user's own git
    # command in that checkout (nor fail on a read-only one), so optional locks are off.
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                                text=True, check=True, timeout=10, env=env).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True, timeout=10, env=env).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{commit}+dirty" if dirty else commit


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, str | int]:
    """The facts that make timings and float results comparable between machines."""
    import torch

    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count() or 0,
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none",
        "python": platform.python_version(),
        "torch": torch.__version__,
        "platform": platform.platform(terse=True),
    }


def describe(seed: int) -> dict:
    """The provenance record of one run: commit, seed and machine."""
    return {"commit": git_commit(), "seed": seed, "machine": machine()}


def peak_rss_gib() -> float:
    """Peak resident memory of this process and its finished children, in GiB (Linux: ru_maxrss in KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    scale = 1024**3 if sys.platform == "darwin" else 1024**2
    return max(own, children) / scale
