"""What verifying the cache's checksums costs training: the extra fraction of data-loading time.

Every shard carries a CRC-32 of its data; the data module checks each shard once per process before training
starts (``tracegs.data.datamodule.verify_shard``), and later reads in the process pay nothing. The cost is
therefore one pass over every shard per training process, set against the data loading that process does
anyway: setting up the data module and serving ``max_steps`` batches.

Measured for each training stage of the embedded default (baseline, Stage 1, Stage 2: steps and batch size
from the composed ``tracegs-train`` config) on a cache of embedded-default shards (prepared here unless it
exists, ``--scenes`` synthetic scenes). A smaller cache than the demo's is read proportionally less: each
shard is served as often as in the demo (``max_steps * batch_size / demo clips`` times), so the ratio is the
demo's. Times are the median of ``--repeats`` runs, each from a cold verification record (warm page cache).

    .venv/bin/python benchmarks/cache_verify.py [--out DIR] [--scenes 2] [--repeats 5]

The last line is one JSON object: ``cache_verify_overhead`` (verification over data loading, all three
stages together) and the same per stage.
"""

from __future__ import annotations

import argparse
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
from tracegs.data.cache_keys import MANIFEST
from tracegs.data.config import DataModuleConfig
from tracegs.data.datamodule import PairedClipDataModule, read_manifest, verify_shard

STAGES = ("baseline", "stage1", "stage2")


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


def load_data(cache: Path, batches: int, batch_size: int) -> float:
    """Seconds to set up the data module (verification included) and serve ``batches`` batches."""
    start = time.perf_counter()
    module = PairedClipDataModule(DataModuleConfig(cache_dir=str(cache), batch_size=batch_size, seed=0))
    module.setup("fit")
    served = 0
    while served < batches:
        for _ in module.train_dataloader():
            served += 1
            if served == batches:
                break
    return time.perf_counter() - start


def verify_all(cache: Path) -> float:
    """Seconds to verify every shard of the cache once (what the data module's setup adds)."""
    shards = [cache / rel for entry in read_manifest(cache)["scenes"].values() for rel in entry["clips"]]
    start = time.perf_counter()
    for shard in shards:
        verify_shard(shard)
    return time.perf_counter() - start


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
    for stage in STAGES:
        steps, batch_size, demo_clips = stage_reads(stage)
        batches = max(1, round(steps * clips / demo_clips))  # each shard read as often as in the demo
        verify, load = [], []
        for _ in range(args.repeats):
            io._verified.clear()  # a fresh process: nothing verified yet
            verify.append(verify_all(cache))
            io._verified.clear()
            load.append(load_data(cache, batches, batch_size))
        seconds_verify, seconds_load = statistics.median(verify), statistics.median(load)
        # load includes its own verification pass: the loading without it is the difference.
        overhead = seconds_verify / (seconds_load - seconds_verify)
        figures[f"cache_verify_overhead_{stage}"] = round(overhead, 4)
        totals["verify"] += seconds_verify
        totals["load"] += seconds_load - seconds_verify
        print(f"{stage:>8s}: {steps} steps x batch {batch_size} over {demo_clips} demo clips -> {batches} batches "
              f"here; verify {seconds_verify * 1e3:.1f} ms, data loading without it "
              f"{(seconds_load - seconds_verify) * 1e3:.1f} ms: overhead {overhead:.3f}")
    total = totals["verify"] / totals["load"]
    print(f"all three stages: overhead {total:.3f} (goal <= 0.05)")
    print(json.dumps({"cache_verify_overhead": round(total, 4), **figures,
                      "shard_megabytes": round(shard_mb, 2), "shards": clips}))


if __name__ == "__main__":
    main()
