"""The cache's index: each shard's manifest (its settings and every scene's files) and their merge into
the cache's ``manifest.json`` by the last shard of a sharded run to finish; a rerun leaves identical files untouched.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from tracegs.data.cache_keys import CACHE_VERSION, MANIFEST
from tracegs.data.config import PrepareConfig
from tracegs.data.preparation.plan import PrepareError, frames_stored, teacher_view_counts
from tracegs.data.splits import view_set_key
from tracegs.io import write_json_atomic

log = logging.getLogger(__name__)


def write_if_changed(data: dict, path: Path) -> None:
    """Atomic JSON write that leaves an identical file untouched (a rerun with no work changes nothing)."""
    if path.is_file():
        try:
            if json.loads(path.read_text()) == json.loads(json.dumps(data)):
                return
        except ValueError:
            pass
    write_json_atomic(data, path)


def manifest_header(cfg: PrepareConfig, backbone_name: str) -> dict:
    return {
        "version": CACHE_VERSION,
        "student_views": list(cfg.student_views),
        "student_snapshots": list(cfg.student_snapshots),
        "teacher_views": sorted({view_set_key(v) for v in teacher_view_counts(cfg)}, key=_view_order),
        "final_snapshot": cfg.fit.iterations,
        "frames_per_clip": cfg.frames_per_clip,
        "frames_stored": frames_stored(cfg),
        "pseudo_target": cfg.pseudo_target,
        "backbone": backbone_name,
    }


def _view_order(key: str) -> float:
    return math.inf if key == "all" else float(key)


def shard_manifest_path(cache_dir: Path, shard_index: int, num_shards: int) -> Path:
    if num_shards == 1:
        return cache_dir / MANIFEST
    return cache_dir / f"manifest_shard{shard_index:03d}_of{num_shards:03d}.json"


def merge_manifests(cache_dir: str | Path, num_shards: int) -> Path | None:
    """Join the manifests of the ``num_shards`` shards of a cache into ``manifest.json`` once every shard has
    written its own (their settings must agree); None, logging how many are left, while some shard has not.

    Every shard calls it as it ends, so the last to finish merges; shards that finish together write the same
    bytes, each atomically, and a rerun leaves an identical manifest untouched."""
    cache_dir = Path(cache_dir)
    parts = [shard_manifest_path(cache_dir, index, num_shards) for index in range(num_shards)]
    left = sum(not part.is_file() for part in parts)
    if left:
        log.info("%s: %d of %d shards still to finish; the last to finish merges their manifests", cache_dir,
                 left, num_shards)
        return None
    merged: dict | None = None
    for part in parts:
        data = json.loads(part.read_text())
        header = {k: v for k, v in data.items() if k != "scenes"}
        if merged is None:
            merged = {**header, "scenes": {}}
        elif header != {k: v for k, v in merged.items() if k != "scenes"}:
            raise PrepareError(f"{part}: settings differ from {parts[0].name}; shards of different runs")
        merged["scenes"].update(data["scenes"])
    merged["scenes"] = dict(sorted(merged["scenes"].items()))
    out = cache_dir / MANIFEST
    write_if_changed(merged, out)
    return out
