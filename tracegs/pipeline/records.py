"""Run records and product locks: a finished product is kept with the settings and input contents that made
it, so an identical run reuses it, a changed input recomputes it and one folder never holds two runs. A root an
older version made keeps its products: a command first renames their folders to today's names."""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from filelock import FileLock
from lightning.fabric.utilities.rank_zero import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from tracegs.config.identity import current_name, differing_keys, scoped_values
from tracegs.content import names_and_bytes_digest, root_relative
from tracegs.errors import ConfigError, require_writable_dir, writable
from tracegs.io import atomic_write, write_json_atomic
from tracegs.stages import stage_table

log = logging.getLogger("tracegs")

RUN_RECORD = "run_identity.json"
LOCK_FILE = ".tracegs.lock"
# How far below the experiment's folder and the data folder product folders lie: ``stage2/<variant>/<run>`` and
# ``eval/<variant>/<data>-<run>`` (conf/stage/stage2.yaml, conf/evaluation/default.yaml), ``cache/<cache>``.
PRODUCT_DEPTH = 3
# The prefix of a record's keys that hold the contents of the earlier products a run loaded.
CONTENT = "content."


def input_digests(cfg: DictConfig, kind: str) -> dict[str, str]:
    """Content digests of the earlier products a ``kind`` run reads (tracegs.content): their content is part of
    the record, so an edit recomputes (the product graph says which, tracegs.stages)."""
    paths = {name: OmegaConf.select(cfg, f"artifacts.{name}") for name in stage_table().record_inputs(kind)}
    return {f"{CONTENT}{name}": names_and_bytes_digest(path) for name, path in paths.items()
            if path is not None and Path(path).exists()}


def _recorded(folder: Path) -> dict[str, Any] | None:
    record = folder / RUN_RECORD
    return json.loads(record.read_text()) if record.is_file() else None


def check_run_record(cfg: DictConfig, kind: str, folder: str | Path) -> bool:
    """Whether ``folder`` holds a finished ``kind`` run of exactly ``cfg`` and of the same input contents.

    A folder whose recorded settings differ (an explicit ``run_dir`` or an older version of the code) is
    refused, naming the differing keys, instead of being resumed or overwritten. A folder whose inputs changed
    since its product was made is cleared for recomputation (its checkpoints would resume the stale run).
    """
    record = Path(folder) / RUN_RECORD
    recorded = _recorded(Path(folder))
    if recorded is None:
        return False
    inputs = input_digests(cfg, kind)
    # Records made before paths were stored relative to the root name them absolutely.
    root = OmegaConf.select(cfg, "paths.root_dir") or "."
    settings = {k: root_relative(v, root) for k, v in recorded.items() if not k.startswith(CONTENT)}
    differing = differing_keys(settings, scoped_values(cfg, kind))
    if differing:
        raise ConfigError(differing[0], f"{folder} holds a run made with other settings "
                          f"({', '.join(differing[:6])} differ): choose another run_dir")
    stale = differing_keys({k: v for k, v in recorded.items() if k.startswith(CONTENT)}, inputs)
    if stale:
        changed = ", ".join(f"artifacts.{key.removeprefix(CONTENT)}" for key in stale)
        log.info("%s: the content of %s changed since this product was made: recomputing it", folder, changed)
        record.unlink()
        shutil.rmtree(Path(folder) / "checkpoints", ignore_errors=True)
        return False
    return True


def reuse_finished(cfg: DictConfig, kind: str, folder: str | Path, product: str | Path) -> bool:
    """Whether ``product`` is the finished product of this very run (same settings and input contents): then
    nothing is done, and the log says so."""
    if check_run_record(cfg, kind, folder) and Path(product).exists():
        log.info("%s: %s already holds this run's product (same settings and inputs): nothing to do", kind, product)
        return True
    return False


@contextlib.contextmanager
def product_lock(folder: str | Path, field: str, shard: tuple[int, int] = (0, 1)) -> Iterator[None]:
    """One job per product folder: a second identical job (another shell, a parallel multirun launcher) waits
    here, then finds the product finished and reuses it. ``shard`` (index, count): the shards of one product
    write their own files and run in parallel, each under its own lock.

    A job that fails leaves no lock file it made, nor the folder if it made it and nothing else is in it (an
    identical job waiting on that lock would fail the same way).

    Only a job's first process (rank 0) takes the lock: the other ranks of a multi-process training job run the
    same command, and one waiting here for rank 0 while rank 0 waits for it to join the process group would
    deadlock."""
    if rank_zero_only.rank != 0 or (Path(folder).is_dir() and not writable(folder)):
        # (A folder nothing can write to, e.g. a read-only copy of a finished root, needs no lock: no job can
        # change it; the step finds its product finished, or refuses in one line where it would write.)
        yield
        return
    folder = require_writable_dir(folder, field)  # a file or a read-only folder: one line naming ``field``
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / (LOCK_FILE if shard[1] == 1 else f"{LOCK_FILE}.shard{shard[0]}of{shard[1]}")
    made_lock = not lock.exists()
    try:
        with FileLock(lock):
            yield
    except BaseException:
        if made_lock:
            lock.unlink(missing_ok=True)
        if created and not any(folder.iterdir()):
            folder.rmdir()
        raise


def relative_to_root(node: object, root: str | Path) -> object:
    """A resolved config container with every absolute path inside ``root`` written relative to it
    (``root_relative``; relative paths, and text that only holds a '/', stay as they are)."""
    if isinstance(node, dict):
        return {key: relative_to_root(value, root) for key, value in node.items()}
    if isinstance(node, list):
        return [relative_to_root(value, root) for value in node]
    return root_relative(node, root) if isinstance(node, str) and node.startswith("/") else node


def write_run_record(cfg: DictConfig, kind: str, folder: str | Path) -> None:
    """Keep beside a finished product the settings that determine it, the contents of the inputs it was made from,
    and the whole resolved config, paths relative to the root: a copy of the root elsewhere keeps the same bytes."""
    folder = Path(folder)
    record = {**scoped_values(cfg, kind), **input_digests(cfg, kind)}
    if _recorded(folder) == json.loads(json.dumps(record)):
        # A product finished again (a rerun, a shard's) keeps the account of the run that made it: its resolved
        # config may hold fields added since, which change nothing it is (a root copied read-only reruns too).
        return
    write_json_atomic(record, folder / RUN_RECORD)
    # Hydra's own node, the command line that happened to make it and the config folders it was composed from
    # are no part of what the product is.
    kept = [key for key in cfg if key not in ("hydra", "command_line", "config_search_path")]
    resolved = OmegaConf.to_container(OmegaConf.masked_copy(cfg, kept), resolve=True)
    with atomic_write(folder / "config.yaml") as tmp:
        tmp.write_text(OmegaConf.to_yaml(relative_to_root(resolved, cfg.paths.root_dir)))


def migrate_older_folders(cfg: DictConfig) -> None:
    """Rename each product folder an older version named (``seed<k>_<overrides typed>-<digest>``) under the
    experiment's folder and the data folder of ``cfg`` to today's name of the same product (``seed<k>-<digest>``),
    contents and all, so a root made by an older version keeps its products (the earlier stages' included).

    Every command runs this once before its config names a folder (tracegs.cli.app.MigrateOlderFolders):
    resolving a config never renames anything. Where nothing can be renamed (a read-only copy of an old root),
    the folders stay where they lie, and the config finds them there (tracegs.config.identity.folder_or_older)."""
    tops = {Path(OmegaConf.select(cfg, key)).expanduser() for key in ("paths.experiment_dir", "paths.data_dir")}
    for older in sorted({folder for top in tops for folder in _older_named(top, PRODUCT_DEPTH)}):
        _rename(older, older.with_name(current_name(older.name)))


def _older_named(folder: Path, depth: int) -> list[Path]:
    """The folders an older version named, up to ``depth`` levels below ``folder`` (their insides not searched)."""
    if depth == 0 or not folder.is_dir():
        return []
    found = []
    for child in sorted(p for p in folder.iterdir() if p.is_dir()):
        found += [child] if current_name(child.name) is not None else _older_named(child, depth - 1)
    return found


def _rename(older: Path, folder: Path) -> None:
    if folder.exists():
        log.warning("%s holds a second copy of %s, made under another spelling of the command line; nothing reads "
                    "it, remove it to reclaim the space", older, folder)
        return
    try:
        older.rename(folder)
    except FileNotFoundError:  # another process of the same command renamed it first
        return
    except OSError:  # a root nothing can rename in: the config finds the folder where it lies
        return
    log.info("%s: renamed to %s (product folders are named by seed and digest only)", older, folder.name)
