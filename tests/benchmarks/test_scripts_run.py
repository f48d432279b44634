"""Every benchmark script runs to its JSON line from a clean checkout (slow: each measures for real).

A benchmark is only read when someone reruns it, so a change elsewhere that breaks one (a new check on the
files it writes, say) would otherwise go unseen until then.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

# stage2_memory.py runs in test_stage2_memory.py, gpu_check.py in tests/rehearsal/test_gpu_check.py (on a machine
# without a GPU it says so instead of printing figures); prepare_data.py prepares the whole demo cache (4 min),
# which the prepare tests cover; clean_clone.py runs `make test` and `make demo` on a clone (12 min), which CI and
# the demo tests cover; pseudo_target_strength.py reads a trained A and a held-out cache, which only a demo or a
# validation run makes.
RUNS = {
    "rasterizer.py": [],
    "restorer.py": [],
    "stage2.py": ["--rollouts", "2", "--steps", "1"],
    "cache_verify.py": ["--scenes", "1", "--repeats", "1", "--out", "{tmp}/cache"],
    "cache_size.py": ["--out", "{tmp}"],
    "paper_gpu_hours.py": [],
    "sfm.py": [],
}


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(RUNS))
def test_benchmark_ends_with_its_json_line(script, tmp_path):
    args = [a.format(tmp=tmp_path) for a in RUNS[script]]
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert isinstance(figures, dict) and figures
