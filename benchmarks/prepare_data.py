"""Time the embedded benchmark's preparation and report the privileged gap.

Prints the wall-clock time of generating the synthetic benchmark and preparing its paired-clip cache
(embedded defaults, from nothing unless --keep), then the PSNR against ground truth of the student
conditions R_s (K = 3, 6, 9 at each student snapshot) and the dense conditions R_d (12, 18, all views, final
snapshot) on the trajectory frames of every clip (reference frames excluded), averaged over clips then
scenes. The last line is one JSON object.

    .venv/bin/python benchmarks/prepare_data.py [--out DIR] [--keep]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from tracegs.data.config import PrepareConfig, SceneSourceConfig, SyntheticConfig
from tracegs.data.preparation.driver import run_prepare
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/bench_prepare")
    parser.add_argument("--keep", action="store_true", help="reuse existing outputs (measures a resumed run)")
    args = parser.parse_args()
    out = Path(args.out)
    if out.exists() and not args.keep:
        shutil.rmtree(out)
    synthetic = SyntheticConfig(root=str(out / "synthetic"))
    source = SceneSourceConfig(root=synthetic.root, preset="synthetic")
    prepare = PrepareConfig(cache_dir=str(out / "cache"), work_dir=str(out / "work"))
    backbone = build_backbone(BackboneConfig())
    start = time.perf_counter()
    manifest_path = run_prepare(prepare, source, backbone, synthetic, progress=True)
    seconds = time.perf_counter() - start
    manifest = json.loads(manifest_path.read_text())
    keys = sorted({k for entry in manifest["scenes"].values() for k in entry["psnr_vs_gt"]})
    psnr = {k: float(np.mean([e["psnr_vs_gt"][k] for e in manifest["scenes"].values()])) for k in keys}
    print(f"prepared {len(manifest['scenes'])} scenes in {seconds:.1f} s")
    for key, value in psnr.items():
        print(f"  PSNR vs GT  {key:>10s}: {value:6.2f} dB")
    print(json.dumps({"prepare_seconds": round(seconds, 1), "num_scenes": len(manifest["scenes"]),
                      **{f"psnr_{k}": round(v, 2) for k, v in psnr.items()}}))


if __name__ == "__main__":
    main()
