"""Content identity: what a user hands in (a capture, a scene, weights) is known by its bytes, never by its path.

A product keyed by a path goes stale when the file at that path changes, and a path changes when the same
files are reached another way (a copied or moved root, a relative spelling). So identities hash file names
(relative to the folder handed in) and bytes, and records name paths relative to the root they live in.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Iterable
from pathlib import Path

DIGEST_CHARS = 16
_CHUNK = 1 << 20
# The parts of a COLMAP scene folder its products depend on: the photos and the reconstruction.
SCENE_PARTS = ("images", "sparse")
# Marks a value stored relative to the run's root (paths.root_dir) in a record or an identity.
ROOT_MARK = "<root>"
# The photo formats structure-from-motion reads: those pycolmap 4.2's image reader decodes (it skips WebP
# without a word, so a WebP photo is listed with the other files a capture folder holds, and ignored aloud).
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file())
    return [path] if path.is_file() else []


def _stamp(files: Iterable[Path]) -> tuple:
    return tuple((str(f), f.stat().st_size, f.stat().st_mtime_ns) for f in files)


@functools.lru_cache(maxsize=64)
def _digest_of(base: Path, stamp: tuple) -> str:
    # Keyed by (name, size, mtime) of every file: one command asks for the same digest several times.
    sha = hashlib.sha256()
    for name, _, _ in stamp:
        file = Path(name)
        sha.update(file.relative_to(base).as_posix().encode() if file != base else b"")
        sha.update(b"\0")
        with file.open("rb") as handle:
            while chunk := handle.read(_CHUNK):
                sha.update(chunk)
    return sha.hexdigest()[:DIGEST_CHARS]


def names_and_bytes_digest(path: str | Path, parts: Iterable[str] = ()) -> str:
    """Digest (``DIGEST_CHARS`` hex digits of SHA-256) of the names and bytes of a file or a folder's files (only its
    sub-folders ``parts``, if given): each file's path relative to ``path``, a NUL, then its bytes. Renaming a file
    inside the folder changes it (contrast :func:`tracegs.io.bytes_digest`, which reads bytes alone)."""
    base = Path(path).expanduser().resolve()
    files = [f for part in parts for f in _files(base / part)] if parts else _files(base)
    return _digest_of(base, _stamp(files))


def scene_digest(scene_dir: str | Path) -> str:
    """Digest of a COLMAP scene folder's images and ``sparse/`` reconstruction."""
    return names_and_bytes_digest(scene_dir, SCENE_PARTS)


def photo_folder(capture: str | Path) -> Path:
    """Where a capture folder without a reconstruction keeps its photos: ``images/`` when it has one, else itself."""
    capture = Path(capture).expanduser().resolve()
    return capture / "images" if (capture / "images").is_dir() else capture


def capture_files(capture: str | Path) -> tuple[list[Path], list[Path]]:
    """(photos, other files) directly in a capture's :func:`photo_folder`, each in name order."""
    files = sorted(p for p in photo_folder(capture).iterdir() if p.is_file() and not p.name.startswith("."))
    photos = [p for p in files if p.suffix.lower() in PHOTO_SUFFIXES]
    return photos, [p for p in files if p.suffix.lower() not in PHOTO_SUFFIXES]


def capture_digest(capture: str | Path) -> str:
    """Digest of a capture folder: its images and reconstruction when it holds one (``sparse/``), else the names
    and bytes of its photos alone (the other files in it are not read, so they change nothing)."""
    capture = Path(capture).expanduser().resolve()
    if (capture / "sparse").is_dir():
        return scene_digest(capture)
    return _digest_of(photo_folder(capture), _stamp(capture_files(capture)[0]))


def root_relative(value: object, root: str | Path) -> object:
    """``value`` as ``<root>/<relative path>`` when it is a path inside ``root``, else unchanged."""
    if not isinstance(value, str) or "/" not in value or value.startswith(ROOT_MARK):
        return value
    try:
        relative = Path(value).expanduser().resolve().relative_to(Path(root).expanduser().resolve())
    except (ValueError, OSError):
        return value
    return f"{ROOT_MARK}/{relative.as_posix()}"
