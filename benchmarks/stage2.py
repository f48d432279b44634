"""Stage-2 memory modes side by side: peak memory and step time of ``retain`` vs ``stepwise`` for several N.

Usage: ``.venv/bin/python benchmarks/stage2.py [--batch 2] [--steps 3] [--rollouts 2 5 10 20]``

What is measured (embedded tiny restorer, CPU, one intra-op thread):
- step time: median CPU time (``time.process_time``; with one thread it is the work done, unaffected by
  other processes sharing the machine, which wall time is not -- wall time is printed too) of a full
  Lightning training step (rollout, N teacher + N student evaluations,
  backward, clipping, AdamW) after one warm-up step;
- irreducible work: N x (one student forward + backward at a visited state) + N x (one no-grad teacher
  forward), each timed alone with plain torch calls in the same process; overhead ratio = step time / that;
- peak memory: CPU tensors have no allocator statistics like ``torch.cuda.max_memory_allocated``, so we
  use the kernel's resident-set high-water mark: before each step we reset it (``echo 5 >
  /proc/self/clear_refs``), read the resident set size, and after the step read ``VmHWM``; the peak is the
  difference (MiB). Each (mode, N) runs in its own fresh process with ``MALLOC_MMAP_THRESHOLD_=65536``, so
  every tensor above 64 KiB is its own mapping that returns to the kernel when freed; RSS then follows live
  tensor memory instead of malloc's cached heap. The figure still includes allocator slack and the
  transient buffers of kernels, so it is an upper bound on live tensor bytes, not an exact count.
- times come from a second fresh process per (mode, N) with glibc's default allocator: under the mmap
  threshold every large tensor is a new mapping whose page faults add system time in proportion to the
  number of allocations, which differs between the modes (measured: 37 s of system time in a 2 min run,
  and ratios that moved by up to 25% between identical runs).
The last printed line is one JSON object (ratios of the worst case over N where a single number is asked).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from queue import Empty

import lightning as L

MMAP_THRESHOLD = "65536"


def _status(field: str) -> int:
    """A ``/proc/self/status`` field in KiB."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")


def _base():
    """(backbone config, the measured step's frozen base: the embedded transformer, random from seed 0). The
    Stage-1 adapter is made on this same base, whose identity its file records and Stage 2 checks."""
    import torch

    from tracegs.restorer.build import create_transformer
    from tracegs.restorer.config import BackboneConfig

    cfg = BackboneConfig()
    torch.manual_seed(0)
    return cfg, create_transformer(cfg.transformer).requires_grad_(False)


def _build(mode: str, rollout: int, batch_size: int, adapter: Path):
    from tracegs.restorer.schedules import build_schedule
    from tracegs.training.config import OptimizerConfig
    from tracegs.training.stage2 import Stage2DistillationModule

    cfg, transformer = _base()
    tc = cfg.transformer
    module = Stage2DistillationModule(
        transformer,
        build_schedule(cfg.schedule),
        adapter,
        OptimizerConfig(lr=1e-4, grad_clip=1.0),
        rollout_steps=rollout,
        deploy_steps=max(cfg.schedule.deploy_steps, rollout),
        memory_mode=mode,
    )
    refs = 2 * (6 * 9)  # two reference views of 48x72 pixels in 8x8 patches (embedded encoder)
    return module, random_batch(tc, tc.sample_frames, refs, batch_size, seed=1)


def random_batch(tc, frames: int, refs: int, batch_size: int, seed: int) -> dict:
    """Random Stage-2 inputs at a transformer config's shapes: ``frames`` latent frames, ``refs`` reference tokens."""
    import torch

    g = torch.Generator().manual_seed(seed)
    latent = (batch_size, frames, tc.latent_channels, tc.sample_height, tc.sample_width)
    return {
        "student_cond": torch.randn(latent, generator=g),
        "teacher_cond": torch.randn(latent, generator=g),
        "target": torch.randn(latent, generator=g),
        "ref_2d": torch.randn(batch_size, refs, tc.ref_2d_dim, generator=g),
        "ref_3d": torch.randn(batch_size, refs, tc.ref_3d_dim, generator=g),
        "text": torch.randn(batch_size, tc.max_text_seq_length, tc.text_embed_dim, generator=g),
    }


class _StepProbe(L.Callback):
    """Lightning callback measuring wall time and resident-set peak of every training step."""

    def __init__(self):
        super().__init__()
        self.cpu_times: list[float] = []
        self.wall_times: list[float] = []
        self.peaks_kib: list[int] = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        _reset_peak()
        self._rss = _status("VmRSS")
        self._cpu, self._wall = time.process_time(), time.perf_counter()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.cpu_times.append(time.process_time() - self._cpu)
        self.wall_times.append(time.perf_counter() - self._wall)
        self.peaks_kib.append(_status("VmHWM") - self._rss)


def _irreducible(module, batch, rollout: int, repeats: int) -> float:
    """N x (student forward + backward) + N x (teacher forward), each evaluation timed alone."""
    import torch

    from tracegs.restorer.adapters import activate
    from tracegs.training.stage2 import STUDENT, TEACHER

    schedule = module.schedule
    state = torch.randn_like(batch["target"])
    t = schedule.timesteps(module.deploy_steps)[1]

    def evaluate(cond):
        return module.predict(state, batch[cond], t, batch, return_retrieval=module.lambda_ret != 0)

    student_times, teacher_times = [], []
    for _ in range(repeats + 1):  # first round is warm-up
        activate(module.transformer, STUDENT)
        start = time.process_time()
        out = evaluate("student_cond")
        (out.velocity.square().mean() + out.retrieval.square().mean()).backward()
        student_times.append(time.process_time() - start)
        activate(module.transformer, TEACHER)
        start = time.process_time()
        with torch.no_grad():
            evaluate("teacher_cond")
        teacher_times.append(time.process_time() - start)
    activate(module.transformer, STUDENT)
    for p in module.trainable_parameters():
        p.grad = None
    return rollout * (statistics.median(student_times[1:]) + statistics.median(teacher_times[1:]))


def _measure(mode: str, rollout: int, batch_size: int, steps: int, adapter: str, queue) -> None:
    import torch
    from torch.utils.data import DataLoader

    torch.set_num_threads(1)
    module, batch = _build(mode, rollout, batch_size, Path(adapter))
    probe = _StepProbe()
    trainer = L.Trainer(
        accelerator="cpu", devices=1, max_steps=steps + 1, logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, callbacks=[probe],
    )
    trainer.fit(module, train_dataloaders=DataLoader([batch], batch_size=None))
    irreducible = _irreducible(module, batch, rollout, repeats=max(3, steps))
    queue.put({
        "step_s": statistics.median(probe.cpu_times[1:]),
        "wall_s": statistics.median(probe.wall_times[1:]),
        "peak_mib": max(probe.peaks_kib[1:]) / 1024,
        "irreducible_s": irreducible,
    })


def _make_adapter(path: Path) -> None:
    """A random Stage-1 adapter on the measured step's base."""
    import torch

    from tracegs.restorer.adapters import adapter_parameters, add_adapter, save_adapter
    from tracegs.stages import Product

    cfg, transformer = _base()
    add_adapter(transformer, "aligned", cfg.lora)
    with torch.no_grad():
        for p in adapter_parameters(transformer, "aligned"):
            p.normal_(0.0, 0.02)
    save_adapter(transformer, "aligned", path, stage=Product.stage1)


def _run_worker(mode: str, rollout: int, args, adapter: Path, mmap_threshold: bool) -> dict:
    return in_fresh_process(_measure, (mode, rollout, args.batch, args.steps, str(adapter)), f"{mode} N={rollout}",
                            mmap_threshold)


def in_fresh_process(target, args: tuple, label: str, mmap_threshold: bool):
    """``target(*args, queue)`` in a fresh spawned process, returning what it puts on the queue; glibc reads
    MALLOC_MMAP_THRESHOLD_ when that process starts."""
    if mmap_threshold:
        os.environ["MALLOC_MMAP_THRESHOLD_"] = MMAP_THRESHOLD
    else:
        os.environ.pop("MALLOC_MMAP_THRESHOLD_", None)
    context = mp.get_context("spawn")
    queue = context.Queue()
    worker = context.Process(target=target, args=(*args, queue))
    worker.start()
    while True:  # a worker that dies puts nothing on the queue: poll, so its failure ends the benchmark
        try:
            result = queue.get(timeout=1.0)
            break
        except Empty:
            if not worker.is_alive():
                result = None
                break
    worker.join()
    if worker.exitcode != 0 or result is None:
        sys.exit(f"measurement of {label} failed (exit code {worker.exitcode})")
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--steps", type=int, default=3, help="measured steps per (mode, N) after one warm-up")
    parser.add_argument("--rollouts", type=int, nargs="+", default=[2, 5, 10, 20])
    args = parser.parse_args(argv)
    if not Path("/proc/self/clear_refs").exists():
        sys.exit("benchmarks/stage2.py needs Linux /proc/self/clear_refs to reset the peak resident set size")
    results: dict[tuple[str, int], dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        adapter = Path(tmp) / "stage1_adapter.safetensors"
        _make_adapter(adapter)
        for rollout in args.rollouts:
            for mode in ("retain", "stepwise"):
                memory = _run_worker(mode, rollout, args, adapter, mmap_threshold=True)
                timing = _run_worker(mode, rollout, args, adapter, mmap_threshold=False)
                results[(mode, rollout)] = {**timing, "peak_mib": memory["peak_mib"]}

    print(f"Stage-2 step, embedded tiny restorer, batch {args.batch}, CPU 1 thread, median of {args.steps} steps "
          "(times are CPU seconds unless marked wall)")
    print(f"{'N':>3} | {'retain peak MiB':>15} {'stepwise peak MiB':>17} | {'retain cpu s':>12} "
          f"{'stepwise cpu s':>14} {'stepwise/retain':>15} | {'irreducible s':>13} {'overhead':>8} | "
          f"{'retain wall s':>13} {'stepwise wall s':>15}")
    time_ratios, overheads = {}, {}
    for rollout in args.rollouts:
        retain, stepwise = results[("retain", rollout)], results[("stepwise", rollout)]
        time_ratios[rollout] = stepwise["step_s"] / retain["step_s"]
        irreducible = (retain["irreducible_s"] + stepwise["irreducible_s"]) / 2
        overheads[rollout] = stepwise["step_s"] / irreducible
        print(f"{rollout:>3} | {retain['peak_mib']:>15.1f} {stepwise['peak_mib']:>17.1f} | {retain['step_s']:>12.3f} "
              f"{stepwise['step_s']:>14.3f} {time_ratios[rollout]:>15.3f} | {irreducible:>13.3f} "
              f"{overheads[rollout]:>8.3f} | {retain['wall_s']:>13.3f} {stepwise['wall_s']:>15.3f}")
    lo, hi = min(args.rollouts), max(args.rollouts)
    summary = {
        f"stepwise_mem_ratio_{hi}_{lo}": results[("stepwise", hi)]["peak_mib"] / results[("stepwise", lo)]["peak_mib"],
        f"retain_mem_ratio_{hi}_{lo}": results[("retain", hi)]["peak_mib"] / results[("retain", lo)]["peak_mib"],
        "stepwise_over_retain_time": max(time_ratios.values()),
        "overhead_ratio": max(overheads.values()),
        "stepwise_over_retain_time_by_n": {str(n): round(r, 4) for n, r in time_ratios.items()},
        "overhead_ratio_by_n": {str(n): round(r, 4) for n, r in overheads.items()},
        "peak_mib": {f"{m}_{n}": round(v["peak_mib"], 2) for (m, n), v in results.items()},
        "step_cpu_s": {f"{m}_{n}": round(v["step_s"], 4) for (m, n), v in results.items()},
        "step_wall_s": {f"{m}_{n}": round(v["wall_s"], 4) for (m, n), v in results.items()},
        "batch": args.batch,
    }
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
