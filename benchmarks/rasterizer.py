"""Rasterizer benchmark: the compiled and the tile-culled PyTorch backends against the naive dense reference.

For 1k, 5k and 20k random Gaussians rendered at 96x144, measures one forward+backward pass (loss = sum of the
squared image) of `render(..., backend="compiled")`, `backend="torch"` and `backend="dense"` (every Gaussian
evaluated at every pixel), side by side in one run (each a whole render: projection, SH colour and
compositing; the compiled backend runs all three in C++), the largest image difference of each tiled backend
to the dense one, and how far the compiled backend's gradients are from the dense reference's.

Method, so the figures can be read correctly:
- every (backend, size) runs in its own fresh subprocess with one intra-op thread; the compiled backend's first
  call (loading, or on a fresh machine compiling, its library) is reported apart as `first_call_ms` and the
  repeats after it are timed, as for the other backends, whose first call is timed with the repeats;
- time = median over repeats of the process CPU time (the machine is shared, so wall time mostly measures the
  neighbours; CPU time of a single-threaded process does not), wall time is printed too;
- peak memory = the process's peak resident set size (VmHWM, reset through /proc/self/clear_refs just before
  the first timed render, so building the scene's initial scales does not count) minus its resident size
  then, i.e. everything the forward+backward pass allocated at its peak, tensors and
  allocator overhead included (tracemalloc cannot see torch's allocations);
- gradient agreement: for each parameter (means, scales, rotations, opacities, colours = SH coefficients),
  max |grad_compiled - grad_dense| / max |grad_dense|, the largest over parameters and sizes;
- the dense reference at 20k would hold ~20 float32 tensors of 20000 x 13824 elements (~22 GB), so it is
  skipped there and reported as null.

Last line: JSON with speedup_5k (dense / torch), speedup_vs_torch_5k (torch / compiled), memory_ratio_5k (torch
/ dense peak), max_abs_diff (torch vs dense) and max_abs_diff_compiled (compiled vs dense) over the sizes where
dense ran, max_rel_grad_diff, plus the per-size figures.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WIDTH, HEIGHT = 144, 96
SIZES = (1000, 5000, 20000)
DENSE_LIMIT = 5000
REPEATS = {"compiled": 5, "torch": 5, "dense": 2}
GRADIENTS = {"means": "means", "scales": "log_scales", "rotations": "quats", "opacities": "opacity_logits",
             "colours_dc": "sh_dc", "colours_rest": "sh_rest"}


def peak_rss_kb() -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))


def current_rss_kb() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def worker(backend: str, n: int, image_path: str) -> None:
    """Run in a fresh process: build the scene, time fwd+bwd, report peak memory, save the image and
    gradients."""
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

    first_call_ms = None
    if backend == "compiled":  # load (or compile) the library outside the timed repeats
        start = time.perf_counter()  # wall time: a compile runs in child processes
        render(model, camera, background, backend=backend).image.sum().backward()
        first_call_ms = 1e3 * (time.perf_counter() - start)
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")  # reset the peak resident size to the current one
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
    peak = peak_rss_kb() - baseline
    grads = {f"grad_{name}": getattr(model, attribute).grad for name, attribute in GRADIENTS.items()}
    save_safetensors_atomic({"image": image, **grads}, image_path)
    print(json.dumps({"cpu_ms": 1e3 * statistics.median(cpu_times), "wall_ms": 1e3 * statistics.median(wall_times),
                      "peak_mb": peak / 1024.0, "first_call_ms": first_call_ms}))


def run_worker(backend: str, n: int, image_path: Path) -> dict:
    done = subprocess.run([sys.executable, __file__, "--worker", backend, str(n), str(image_path)],
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    from safetensors.torch import load_file

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in SIZES:
            row = {backend: run_worker(backend, n, Path(tmp) / f"{backend}_{n}.safetensors")
                   for backend in ("compiled", "torch")}
            if n <= DENSE_LIMIT:
                row["dense"] = run_worker("dense", n, Path(tmp) / f"dense_{n}.safetensors")
                reference = load_file(str(Path(tmp) / f"dense_{n}.safetensors"))
                tiled = load_file(str(Path(tmp) / f"torch_{n}.safetensors"))
                compiled = load_file(str(Path(tmp) / f"compiled_{n}.safetensors"))
                row["max_abs_diff"] = (tiled["image"] - reference["image"]).abs().max().item()
                row["max_abs_diff_compiled"] = (compiled["image"] - reference["image"]).abs().max().item()
                row["rel_grad_diff_compiled"] = {
                    name: ((compiled[f"grad_{name}"] - reference[f"grad_{name}"]).abs().max()
                           / reference[f"grad_{name}"].abs().max()).item() for name in GRADIENTS}
            results[n] = row

    print(f"{'gaussians':>9} | {'compiled cpu ms':>15} {'peak MB':>8} {'first call ms':>13} | {'vs torch':>8} "
          f"{'max|diff|':>9} {'grad rel':>9}")
    for n, row in results.items():
        c = row["compiled"]
        grads = f"{max(row['rel_grad_diff_compiled'].values()):9.2e}" if "dense" in row else f"{'':>9}"
        diff = f"{row['max_abs_diff_compiled']:9.2e}" if "dense" in row else f"{'':>9}"
        print(f"{n:>9} | {c['cpu_ms']:15.1f} {c['peak_mb']:8.1f} {c['first_call_ms']:13.1f} | "
              f"{row['torch']['cpu_ms'] / c['cpu_ms']:7.1f}x {diff} {grads}")
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
        "speedup_vs_torch_5k": five["torch"]["cpu_ms"] / five["compiled"]["cpu_ms"],
        "memory_ratio_5k": five["torch"]["peak_mb"] / five["dense"]["peak_mb"],
        "max_abs_diff": max(row["max_abs_diff"] for row in results.values() if "max_abs_diff" in row),
        "max_abs_diff_compiled": max(row["max_abs_diff_compiled"] for row in results.values() if "dense" in row),
        "max_rel_grad_diff": max(max(row["rel_grad_diff_compiled"].values()) for row in results.values()
                                 if "dense" in row),
        "resolution": [HEIGHT, WIDTH],
        "per_size": {str(n): row for n, row in results.items()},
        "time_measure": "median process CPU time, 1 thread, fresh subprocess per run",
        "memory_measure": "peak RSS (VmHWM, reset before the first timed render) minus RSS then",
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--worker":
        worker(sys.argv[2], int(sys.argv[3]), sys.argv[4])
    else:
        main()
