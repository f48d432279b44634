"""Rasterizer benchmark: the tile-culled PyTorch backend against the naive dense reference.

For 1k, 5k and 20k random Gaussians rendered at 96x144, measures one forward+backward pass (loss = sum of the
squared image) of `render(..., backend="torch")` and of `backend="dense"` (every Gaussian evaluated at every
pixel), side by side in one run, and the largest image difference between the two.

Method, so the figures can be read correctly:
- every (backend, size) runs in its own fresh subprocess with one intra-op thread;
- time = median over repeats of the process CPU time (the machine is shared, so wall time mostly measures the
  neighbours; CPU time of a single-threaded process does not), wall time is printed too;
- peak memory = the process's peak resident set size (getrusage ru_maxrss) minus its resident size just
  before the first render, i.e. everything the forward+backward pass allocated at its peak, tensors and
  allocator overhead included (tracemalloc cannot see torch's allocations);
- the dense reference at 20k would hold ~20 float32 tensors of 20000 x 13824 elements (~22 GB), so it is
  skipped there and reported as null.

Last line: JSON with speedup_5k, memory_ratio_5k (torch / dense peak), max_abs_diff (over the sizes where
both ran), plus the per-size figures.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WIDTH, HEIGHT = 144, 96
SIZES = (1000, 5000, 20000)
DENSE_LIMIT = 5000
REPEATS = {"torch": 5, "dense": 2}


def current_rss_kb() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def worker(backend: str, n: int, image_path: str) -> None:
    """Run in a fresh process: build the scene, time fwd+bwd, report peak memory, save the image."""
    import torch

    from tracegs.io import save_safetensors_atomic
    from tracegs.splat.cameras import Camera
    from tracegs.splat.gaussians import GaussianModel
    from tracegs.splat.render import render

    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(0)
    model = GaussianModel.random(n, radius=1.0, generator=generator, initial_opacity=0.5)
    with torch.no_grad():
        model.quats.copy_(torch.randn(n, 4, generator=generator))
        model.log_scales.add_(0.3 * torch.randn(n, 3, generator=generator))
        model.opacity_logits.copy_(torch.randn(n, generator=generator))
    camera = Camera.look_at(torch.tensor([0.0, -3.5, 1.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]),
                            fov_x_deg=50.0, width=WIDTH, height=HEIGHT)
    background = torch.tensor([0.2, 0.3, 0.4])

    baseline = current_rss_kb()
    cpu_times, wall_times = [], []
    for _ in range(REPEATS[backend]):
        model.zero_grad(set_to_none=True)
        cpu, wall = time.process_time(), time.perf_counter()
        out = render(model, camera, background, backend=backend)
        out.image.square().sum().backward()
        cpu_times.append(time.process_time() - cpu)
        wall_times.append(time.perf_counter() - wall)
        image = out.image.detach()
        del out
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - baseline
    save_safetensors_atomic({"image": image}, image_path)
    print(json.dumps({"cpu_ms": 1e3 * statistics.median(cpu_times), "wall_ms": 1e3 * statistics.median(wall_times),
                      "peak_mb": peak / 1024.0}))


def run_worker(backend: str, n: int, image_path: Path) -> dict:
    done = subprocess.run([sys.executable, __file__, "--worker", backend, str(n), str(image_path)],
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    from safetensors.torch import load_file

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in SIZES:
            row = {"torch": run_worker("torch", n, Path(tmp) / f"torch_{n}.safetensors")}
            if n <= DENSE_LIMIT:
                row["dense"] = run_worker("dense", n, Path(tmp) / f"dense_{n}.safetensors")
                ours = load_file(str(Path(tmp) / f"torch_{n}.safetensors"))["image"]
                reference = load_file(str(Path(tmp) / f"dense_{n}.safetensors"))["image"]
                row["max_abs_diff"] = (ours - reference).abs().max().item()
            results[n] = row

    print(f"{'gaussians':>9} | {'torch cpu ms':>12} {'wall ms':>8} {'peak MB':>8} | {'dense cpu ms':>12} "
          f"{'wall ms':>8} {'peak MB':>8} | {'speedup':>7} {'mem ratio':>9} {'max|diff|':>9}")
    for n, row in results.items():
        t, d = row["torch"], row.get("dense")
        dense_cols = (f"{d['cpu_ms']:12.1f} {d['wall_ms']:8.1f} {d['peak_mb']:8.1f}" if d
                      else f"{'skipped':>12} {'':>8} {'':>8}")
        ratio_cols = (f"{d['cpu_ms'] / t['cpu_ms']:7.1f}x {t['peak_mb'] / d['peak_mb']:9.3f} {row['max_abs_diff']:9.2e}"
                      if d else f"{'':>8} {'':>9} {'':>9}")
        print(f"{n:>9} | {t['cpu_ms']:12.1f} {t['wall_ms']:8.1f} {t['peak_mb']:8.1f} | {dense_cols} | {ratio_cols}")

    five = results[5000]
    summary = {
        "speedup_5k": five["dense"]["cpu_ms"] / five["torch"]["cpu_ms"],
        "memory_ratio_5k": five["torch"]["peak_mb"] / five["dense"]["peak_mb"],
        "max_abs_diff": max(row["max_abs_diff"] for row in results.values() if "max_abs_diff" in row),
        "resolution": [HEIGHT, WIDTH],
        "per_size": {str(n): row for n, row in results.items()},
        "time_measure": "median process CPU time, 1 thread, fresh subprocess per run",
        "memory_measure": "peak RSS (ru_maxrss) minus RSS before the first render",
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--worker":
        worker(sys.argv[2], int(sys.argv[3]), sys.argv[4])
    else:
        main()
