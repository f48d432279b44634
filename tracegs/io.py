"""Atomic file writes shared by every stage: nothing half-written survives an interrupted run."""

from __future__ import annotations

import contextlib
import errno
import filecmp
import hashlib
import json
import mmap
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
import xxhash
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from tracegs.errors import InputFileError, NonFiniteError, one_line, write_failure


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
    """Yield a temporary path next to ``path``; on success rename it over ``path``, unless ``path`` already holds
    the same bytes: then it is left as it is (a rerun that makes a file again does not touch it).

    The temporary file lives in the same directory so that ``os.replace`` is an atomic rename
    on POSIX. On any exception the temporary file is removed and ``path`` is left untouched. An existing ``path``
    in a folder nothing can be written to (a read-only copy of a finished root) is made again in the system's
    temporary folder and compared: the same bytes need no write, other bytes are refused in one line.
    """
    target = Path(path)
    refused: OSError | None = None  # why the folder takes no file, when the product is made again aside
    with refused_writes_named(target):
        if not target.parent.is_dir():
            target.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        except OSError as error:
            if not target.is_file() or error.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise
            refused = error
            fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        with refused_writes_named(target):
            yield tmp
            if target.is_file() and filecmp.cmp(tmp, target, shallow=False):
                return
            if refused is not None:
                raise refused
            # After the writer: some writers (safetensors) create the file anew instead of reusing ours.
            _with_umask_permissions(tmp, 0o666)
            os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def refused_writes_named(target: Path) -> Iterator[None]:
    """Turn the machine refusing a write (disk full, file too large, read-only, no permission) into the one-line
    :class:`OutputPathError` naming ``target`` and what to do; other errors pass unchanged."""
    try:
        yield
    except (OSError, SafetensorError) as error:
        failure = write_failure(target, as_os_error(error))
        if failure is None:
            raise
        raise failure from error


def as_os_error(error: BaseException) -> OSError:
    """The ``OSError`` behind ``error``: safetensors' Rust writer reports one as text ("... (os error 28)")."""
    if isinstance(error, OSError):
        return error
    found = re.search(r"\(os error (\d+)\)", str(error))
    code = int(found.group(1)) if found else 0
    return OSError(code, os.strerror(code) if code else str(error))


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary directory next to ``path``; on success it takes ``path``'s place.

    For products made of several files (a diffusers model directory, a COLMAP model, a scene): a
    complete directory at ``path`` always means a finished product. An existing ``path`` is moved
    aside first and deleted only after the new one is in place. A product that fails takes with it the
    folders made to hold it, where they are still empty: a refused command leaves nothing behind.
    """
    target = Path(path)
    made = [parent for parent in target.parents if not parent.exists()]
    with refused_writes_named(target):
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    _with_umask_permissions(staging, 0o777)
    try:
        with refused_writes_named(target):
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
            for parent in made:  # nearest first
                with contextlib.suppress(OSError):  # no longer empty: another product lives there now
                    parent.rmdir()


def save_safetensors_atomic(
    tensors: dict[str, torch.Tensor], path: str | os.PathLike, metadata: dict[str, str] | None = None
) -> None:
    """Write a safetensors file atomically (contiguous CPU copies, as safetensors requires).

    A tensor holding NaN or infinity is refused (nothing is written): a cache shard or an adapter with
    non-finite values would poison every run that reads it. The header's metadata carries a checksum (XXH3) of each
    tensor's bytes (:data:`CHECKSUM_KEY`), so a reader can tell a file whose bytes changed after it was written.
    """
    payload = {name: t.detach().to("cpu").contiguous() for name, t in tensors.items()}
    bad = non_finite_keys(payload)
    if bad:
        raise NonFiniteError(path, f"non-finite values in tensors {bad[:8]}; the file was not written",
                             "check the inputs that produced them (images, fits, learning rate)")
    with atomic_write(path) as tmp:
        save_file(payload, str(tmp), metadata={**(metadata or {}), CHECKSUM_KEY: _placeholder_checksums(payload)})
        seal_header(tmp)


def non_finite_keys(tensors: Mapping[str, torch.Tensor]) -> list[str]:
    """Names of the floating-point tensors that hold a NaN or an infinity."""
    return [name for name, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]


# XXH3 (xxhash) per tensor: the checksums guard against damage (a disk, a copy, an edit by hand), not
# against tampering, and every training process pays for them before it starts, so the fastest well-kept
# hash: 22 GB/s on the 2-core VM, against 4 for zlib's CRC-32 and 1.8 for SHA-256. A reader checks only the
# tensors it reads (training: the latents and tokens, half of an embedded shard).
CHECKSUM_KEY = "data_xxh3_64"  # metadata: JSON {tensor name: 16 hex digits}
CHECKSUM_DIGITS = 16


def _header(handle) -> tuple[int, dict]:
    length = int.from_bytes(handle.read(8), "little")
    return length, json.loads(handle.read(length))


def _placeholder_checksums(names) -> str:
    """The checksum entry with every digit zero: as long as the real one, so it can be filled in in place."""
    return json.dumps({name: "0" * CHECKSUM_DIGITS for name in sorted(names)})


def _tensor_checksums(handle, length: int, header: dict, names) -> dict[str, str]:
    """XXH3-64 (16 hex digits) of each named tensor's bytes, read through a memory map (no copy)."""
    start = 8 + length
    with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as mapped, memoryview(mapped) as view:
        sums = {}
        for name in names:
            begin, end = header[name]["data_offsets"]
            sums[name] = xxhash.xxh3_64_hexdigest(view[start + begin:start + end])
        return sums


def seal_header(path: Path) -> None:
    """Rewrite a safetensors header in place: ``__metadata__`` keys sorted and the tensors' checksums filled in.

    safetensors serialises the metadata map in hash order, which differs between processes, so the same
    tensors and metadata would give different bytes (a resumed or parallel run could not be compared
    with an uninterrupted one byte for byte). The library has no option for a fixed order, hence this.
    Reordering the members of a JSON object and replacing the checksum placeholder by digests of the same
    length keep the header's length, so the data offsets stay valid.
    """
    with open(path, "r+b") as handle:
        length, header = _header(handle)
        names = sorted(k for k in header if k != "__metadata__")
        header["__metadata__"][CHECKSUM_KEY] = json.dumps(_tensor_checksums(handle, length, header, names))
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) > length:
            raise RuntimeError(f"{path}: re-serialised safetensors header grew ({len(text)} > {length} bytes)")
        handle.seek(8)
        handle.write(text.ljust(length))  # the format pads headers with spaces


_verified: set[tuple] = set()


def checksum_problem(path: str | os.PathLike, names: Iterable[str] | None = None) -> str | None:
    """Why the tensors ``names`` (default: all) of a safetensors file cannot be trusted (no checksums, or bytes
    that differ from the checksums written with them), or None. A tensor is checked once per process while the
    file's size and modification time stay the same: a reader that opens a shard again pays nothing more."""
    stat = os.stat(path)
    identity = (os.path.abspath(path), stat.st_ino, stat.st_size, stat.st_mtime_ns)
    try:
        with open(path, "rb") as handle:
            length, header = _header(handle)
            stored = header.get("__metadata__", {}).get(CHECKSUM_KEY)
            if stored is None:
                return "has no data checksums (written by an older version)"
            expected = json.loads(stored)
            wanted = sorted(k for k in header if k != "__metadata__") if names is None else sorted(names)
            todo = [name for name in wanted if (identity, name) not in _verified]
            if todo:
                unlisted = [name for name in todo if name not in expected or name not in header]
                if unlisted:
                    return f"tensors {unlisted[:4]} have no checksum"
                actual = _tensor_checksums(handle, length, header, todo)
                differing = [name for name in todo if actual[name] != expected[name]]
                if differing:
                    return (f"tensors {differing[:4]} differ from the checksums written with them (the file was "
                            "damaged or edited)")
    except (OSError, ValueError, AttributeError, KeyError, TypeError) as error:
        return f"unreadable header ({one_line(error)})"
    _verified.update((identity, name) for name in todo)
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


_digests: dict[tuple, str] = {}


def bytes_digest(path: str | os.PathLike) -> str:
    """SHA-256 (16 hex digits) of a file's bytes, or of a folder's files' bytes end to end in name order, the names
    themselves not hashed: the identity of a restorer's weights and of the demo's tables (contrast
    :func:`tracegs.content.names_and_bytes_digest`). Computed once per process while the files' sizes and
    modification times stay put."""
    path = Path(path)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    key = tuple((str(f.resolve()), f.stat().st_size, f.stat().st_mtime_ns) for f in files)
    if key not in _digests:
        sha = hashlib.sha256()
        for file in files:
            with open(file, "rb") as handle:
                for chunk in iter(lambda: handle.read(1 << 24), b""):  # the files' bytes end to end
                    sha.update(chunk)
        _digests[key] = sha.hexdigest()[:16]
    return _digests[key]


def write_json_atomic(data: Any, path: str | os.PathLike) -> None:
    """Write JSON (indented, keys in insertion order) atomically."""
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
