"""What verifying the cache's checksums costs training: the extra fraction of data-loading time.

Every shard carries a checksum (XXH3) of each tensor; the data module checks the tensors training reads, in every shard,
once per process before training starts (``tracegs.data.datamodule.verify_shard``), and later reads in the
process pay nothing. The cost is one pass over those bytes per training process (the data module's setup with
the check, less the setup with the check switched off), set against the data loading that process does anyway
without it: setting up the data module and serving ``max_steps`` batches.

Measured for each training stage of the embedded default (baseline, Stage 1, Stage 2: steps and batch size
from the composed ``tracegs-train`` config) on a cache of embedded-default shards (prepared here unless it
exists, ``--scenes`` synthetic scenes). A smaller cache than the demo's is read proportionally less: each
shard is served as often as in the demo (``max_steps * batch_size / demo clips`` times), so the ratio is the
demo's. Times are CPU time of this process (``time.process_time``; one thread, the loader in the process, so
other jobs on a shared machine do not inflate them as they do wall time), the median of ``--repeats`` runs,
each from a cold verification record (warm page cache).

    .venv/bin/python benchmarks/cache_verify.py [--out DIR] [--scenes 2] [--repeats 5]

The last line is one JSON object: ``cache_verify_overhead`` (verification over data loading, all three
stages together) and the same per stage.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from tracegs import io
from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.data import datamodule
from tracegs.data.cache_keys import MANIFEST
from tracegs.data.config import DataModuleConfig
from tracegs.data.datamodule import PairedClipDataModule, read_manifest
from tracegs.stages import STAGES


def stage_reads(stage: str) -> tuple[int, int, int]:
    """(max_steps, batch_size, clips in the demo's cache) of a training stage of the embedded default."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"stage={stage}"])
    clips = cfg.data.prepare.clips_per_scene * len(cfg.data.synthetic.train_seeds)
    return int(cfg.stage.max_steps), int(cfg.stage.batch_size), int(clips)


def prepared_cache(out: Path, scenes: int) -> Path:
    """A cache of embedded-default shards under ``out`` (prepared with ``tracegs-prepare`` when missing)."""
    manifests = sorted(out.rglob(MANIFEST))
    if not manifests:
        seeds = ",".join(str(s) for s in range(scenes))
        subprocess.run([str(Path(sys.executable).parent / "tracegs-prepare"), f"paths.root_dir={out.resolve()}",
                        f"data.synthetic.train_seeds=[{seeds}]"], check=True, cwd=out)
        manifests = sorted(out.rglob(MANIFEST))
    return manifests[0].parent


def load_data(cache: Path, batches: int, batch_size: int) -> tuple[float, float]:
    """CPU seconds to set up the data module (where verification happens) and to serve ``batches`` batches."""
    start = time.process_time()
    module = PairedClipDataModule(DataModuleConfig(cache_dir=str(cache), batch_size=batch_size, seed=0))
    module.setup("fit")
    setup = time.process_time() - start
    served = 0
    while served < batches:
        for _ in module.train_dataloader():
            served += 1
            if served == batches:
                break
    return setup, time.process_time() - start - setup


@contextlib.contextmanager
def no_verification():
    """The data module as it was before checksums: the baseline the overhead is measured against."""
    checksum_problem = datamodule.checksum_problem
    datamodule.checksum_problem = lambda path, names=None: None
    try:
        yield
    finally:
        datamodule.checksum_problem = checksum_problem


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/bench_cache_verify")
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)  # as a training process with its data module in the main process
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = prepared_cache(out, args.scenes)
    clips = sum(len(entry["clips"]) for entry in read_manifest(cache)["scenes"].values())
    shard_mb = sum(p.stat().st_size for p in cache.rglob("*.safetensors")) / clips / 2**20
    print(f"cache {cache}: {clips} shards of {shard_mb:.2f} MB")
    totals = {"verify": 0.0, "load": 0.0}
    figures = {}
    for stage in STAGES.names():
        steps, batch_size, demo_clips = stage_reads(stage)
        batches = max(1, round(steps * clips / demo_clips))  # each shard read as often as in the demo
        setup_with, setup_without, serving = [], [], []
        for _ in range(args.repeats):  # interleaved, so a slow spell of the shared machine hits both alike
            io._verified.clear()  # a fresh process: nothing verified yet
            setup_with.append(load_data(cache, batches, batch_size)[0])
            with no_verification():
                setup, serve = load_data(cache, batches, batch_size)
            setup_without.append(setup)
            serving.append(serve)
        # Verification happens in setup only, so the overhead is the difference of the (short) setups: a
        # difference of whole loading times would drown it in the shared machine's noise.
        verify = statistics.median(setup_with) - statistics.median(setup_without)
        loading = statistics.median(setup_without) + statistics.median(serving)
        overhead = verify / loading
        figures[f"cache_verify_overhead_{stage}"] = round(overhead, 4)
        totals["verify"] += verify
        totals["load"] += loading
        print(f"{stage:>8s}: {steps} steps x batch {batch_size} over {demo_clips} demo clips -> {batches} batches "
              f"here; data loading {loading * 1e3:.1f} ms without verification, verification {verify * 1e3:.1f} ms: "
              f"overhead {overhead:.3f}")
    total = totals["verify"] / totals["load"]
    print(f"all three stages: overhead {total:.3f} (goal <= 0.05)")
    print(json.dumps({"cache_verify_overhead": round(total, 4), **figures,
                      "shard_megabytes": round(shard_mb, 2), "shards": clips}))


if __name__ == "__main__":
    main()
