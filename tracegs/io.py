"""Atomic file writes shared by every stage: nothing half-written survives an interrupted run."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from tracegs.errors import InputFileError, NonFiniteError, one_line


def _current_umask() -> int:
    # The only portable way to read the umask is to set it and put it back.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _with_umask_permissions(path: Path, mode: int) -> None:
    """``tempfile`` creates private files (0600) and folders (0700); a product takes the permissions any
    ordinary file would, so colleagues on a shared file system can read what the umask lets them."""
    os.chmod(path, mode & ~_current_umask())


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it over ``path``.

    The temporary file lives in the same directory so that ``os.replace`` is an atomic rename
    on POSIX. On any exception the temporary file is removed and ``path`` is left untouched.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # After the writer: some writers (safetensors) create the file anew instead of reusing ours.
        _with_umask_permissions(tmp, 0o666)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary directory next to ``path``; on success it takes ``path``'s place.

    For products made of several files (a diffusers model directory, a COLMAP model, a scene): a
    complete directory at ``path`` always means a finished product. An existing ``path`` is moved
    aside first and deleted only after the new one is in place.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    _with_umask_permissions(staging, 0o777)
    try:
        yield staging
        if target.exists():
            retired = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
            os.replace(target, retired / target.name)
            os.replace(staging, target)
            shutil.rmtree(retired)
        else:
            os.replace(staging, target)
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def save_safetensors_atomic(
    tensors: dict[str, torch.Tensor], path: str | os.PathLike, metadata: dict[str, str] | None = None
) -> None:
    """Write a safetensors file atomically (contiguous CPU copies, as safetensors requires).

    A tensor holding NaN or infinity is refused (nothing is written): a cache shard or an adapter with
    non-finite values would poison every run that reads it. The header's metadata carries the SHA-256 of the
    data bytes (:data:`CHECKSUM_KEY`), so a reader can tell a file whose bytes changed after it was written.
    """
    payload = {name: t.detach().to("cpu").contiguous() for name, t in tensors.items()}
    bad = non_finite_keys(payload)
    if bad:
        raise NonFiniteError(path, f"non-finite values in tensors {bad[:8]}; the file was not written",
                             "check the inputs that produced them (images, fits, learning rate)")
    with atomic_write(path) as tmp:
        # A placeholder of the digest's length: the real digest then fits into the header in place.
        save_file(payload, str(tmp), metadata={**(metadata or {}), CHECKSUM_KEY: "0" * CHECKSUM_LENGTH})
        seal_header(tmp)


def non_finite_keys(tensors: Mapping[str, torch.Tensor]) -> list[str]:
    """Names of the floating-point tensors that hold a NaN or an infinity."""
    return [name for name, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]


# SHA-256 rather than blake2b: with the CPUs' SHA extensions it hashes about twice as fast (1.8 against
# 0.9 GB/s measured on the 2-core VM), and verification cost is what a reader pays.
CHECKSUM_KEY = "data_sha256"
CHECKSUM_LENGTH = 64


def _header(handle) -> tuple[int, dict]:
    length = int.from_bytes(handle.read(8), "little")
    return length, json.loads(handle.read(length))


def _data_digest(handle) -> str:
    """SHA-256 of everything from the handle's position to the end (the tensors' bytes)."""
    return hashlib.file_digest(handle, "sha256").hexdigest()


def seal_header(path: Path) -> None:
    """Rewrite a safetensors header in place: ``__metadata__`` keys sorted and the data checksum filled in.

    safetensors serialises the metadata map in hash order, which differs between processes, so the same
    tensors and metadata would give different bytes (a resumed or parallel run could not be compared
    with an uninterrupted one byte for byte). The library has no option for a fixed order, hence this.
    Reordering the members of a JSON object and replacing the checksum placeholder by a digest of the same
    length keep the header's length, so the data offsets stay valid.
    """
    with open(path, "r+b") as handle:
        length, header = _header(handle)
        header["__metadata__"][CHECKSUM_KEY] = _data_digest(handle)
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) > length:
            raise RuntimeError(f"{path}: re-serialised safetensors header grew ({len(text)} > {length} bytes)")
        handle.seek(8)
        handle.write(text.ljust(length))  # the format pads headers with spaces


_verified: set[tuple] = set()


def checksum_problem(path: str | os.PathLike) -> str | None:
    """Why ``path``'s tensors cannot be trusted (no checksum, or data bytes that differ from the checksum
    written with them), or None. A file is hashed once per process while its size and modification time
    stay the same: readers that open a shard again (every epoch, every evaluation) pay nothing more."""
    stat = os.stat(path)
    identity = (os.path.abspath(path), stat.st_ino, stat.st_size, stat.st_mtime_ns)
    if identity in _verified:
        return None
    try:
        with open(path, "rb") as handle:
            expected = _header(handle)[1].get("__metadata__", {}).get(CHECKSUM_KEY)
            if expected is None:
                return "has no data checksum (written by an older version)"
            if _data_digest(handle) != expected:
                return "data bytes differ from the checksum written with them (the file was damaged or edited)"
    except (OSError, ValueError, AttributeError) as error:
        return f"unreadable header ({one_line(error)})"
    _verified.add(identity)
    return None


def read_safetensors(path: str | os.PathLike, fix: str) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Every tensor and the metadata of a safetensors file; a missing or damaged file (including one whose
    data differ from the checksum it carries) raises :class:`InputFileError` naming it, followed by ``fix``
    (what the user should do). Files written elsewhere carry no checksum and are read as they are."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "no such file" if not path.exists() else "is not a file", fix)
    try:
        with safe_open(str(path), framework="pt") as handle:
            tensors, metadata = {key: handle.get_tensor(key) for key in handle.keys()}, handle.metadata() or {}
    except (SafetensorError, OSError, ValueError) as error:
        raise InputFileError(path, f"not a readable safetensors file ({one_line(error)})", fix) from error
    problem = checksum_problem(path) if CHECKSUM_KEY in metadata else None
    if problem:
        raise InputFileError(path, problem, fix)
    return tensors, metadata


def write_json_atomic(data: Any, path: str | os.PathLike) -> None:
    """Write JSON (indented, keys in insertion order) atomically."""
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
