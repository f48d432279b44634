"""The tile rasterizer of `rasterize.py` compiled to C++, forward and backward (CPU, float32), and the library
it is built into.

Same inputs, tiles, depth order, 1/255 alpha threshold, 0.99 alpha clamp and transmittance cut-off as
`rasterize_tiles` (`rasterize_compiled.cpp`). The pure-PyTorch backend spends most of its time on the fixed
overhead of many small tensor operations; the compiled loop walks each tile's splats once, updates the tile's
pixels in SIMD registers, stops when the tile is opaque and needs no intermediate tensors, which makes the
compositing more than ten times faster. The same library holds the per-Gaussian projection and SH colour of the
compiled backend (`preprocess_compiled.py`), which in PyTorch would then take half of a render: `render`'s
compiled backend is two compiled autograd nodes, preprocessing and compositing. The compositing reads the visible
Gaussians through an index in depth order, so nothing is gathered or scattered in PyTorch.

Why this tool: `torch.utils.cpp_extension.load` compiles at first use with the C++ compiler and ninja (a
declared dependency) into the torch extensions cache (``~/.cache/torch_extensions``, or
``$TORCH_EXTENSIONS_DIR``), guards the build with a lock file so concurrent processes (forked workers, parallel
pytest) build once and the others wait, and reuses the library afterwards. It is not built at install time
because pip's build isolation would pull a CUDA torch. The sources include no torch headers and expose a plain C
ABI called through ctypes: with ``torch/extension.h`` and pybind11 the one-time compile takes ~45 s on a 2-core
machine, without them a few seconds. numba was the alternative; it is not a dependency here and would
JIT-compile in every fresh worker process. The build directory is named by a hash of the sources and of the
torch installation, so checkouts or venvs with different sources never rebuild a library another process has
loaded. Where that cache cannot be written (HOME is read-only on many clusters and containers), the library is
built in a folder of this user's in the system's temporary folder instead (`writable_extension_cache`), said in one log
line: the same sources and flags make the same library, so a run's numbers do not depend on where it was built.

The kernels are single-threaded: the embedded pipeline already runs one single-threaded fit per core. It is
compiled for tiles of 4, 8 and 16 pixels (`TILE_SIZES`); `rasterize_tiles` uses 4.
Where the library cannot be built (no compiler, no writable folder), `compiled_unavailable()` says why, and
`render.require_available` refuses the backends that need it (`auto` on the CPU included) in one line.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import functools
import hashlib
import logging
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import torch
from torch import Tensor

from tracegs.errors import one_line, out_of_memory, writable
from tracegs.splat.rasterize import OCCLUSION_EPS

SOURCES = tuple(Path(__file__).with_name(name) for name in ("rasterize_compiled.cpp", "preprocess_compiled.cpp"))
# -fopenmp-simd: the pixel loops' `omp simd` hints only (no OpenMP runtime); -fno-trapping-math lets the
# compiler turn float comparisons into vector selects (nothing here reads floating-point exception flags); no
# -march=native, the cache directory may be shared by machines with other CPUs.
COMPILE_FLAGS = ["-O3", "-fopenmp-simd", "-fno-trapping-math"]
log = logging.getLogger(__name__)

TILE_SIZES = (4, 8, 16)  # the instantiations of the C++ template
_float_p = ctypes.POINTER(ctypes.c_float)
_int64_p = ctypes.POINTER(ctypes.c_int64)


def _ninja_on_path() -> None:
    """Put the pip-installed ninja on PATH: torch looks for it there, and a venv's bin is not on PATH unless it is
    activated (make calls .venv/bin/python directly)."""
    if shutil.which("ninja") is None:
        import ninja

        os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")


def writable_extension_cache() -> None:
    """Make sure torch builds extensions in a writable folder: its own cache (``$TORCH_EXTENSIONS_DIR``, else
    ``~/.cache/torch_extensions``) where that is or can be made one, else a folder of this user's in the system's
    temporary folder, said in one log line and exported as ``$TORCH_EXTENSIONS_DIR``, so the worker processes
    started afterwards build and load there without probing and saying it again.

    The temporary folder is shared by every user of the machine, and a library is code this process runs: the
    folder is made private (0700) and refused when someone else owns it or others can write to it."""
    from torch.utils.cpp_extension import get_default_build_root

    default = Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root())
    try:
        default.mkdir(parents=True, exist_ok=True)
        problem = None if writable(default) else "no file can be created there"
    except OSError as error:
        problem = error.strerror or one_line(error)
    if problem is None:
        return
    fallback = Path(tempfile.gettempdir()) / f"tracegs-torch-extensions-{os.getuid()}"
    fallback.mkdir(mode=0o700, exist_ok=True)
    found = fallback.lstat()
    if not stat.S_ISDIR(found.st_mode) or found.st_uid != os.getuid() or found.st_mode & 0o022:
        raise OSError(f"the torch extensions cache {default} is not writable ({problem}) and {fallback} is not a "
                      "private folder of this user's; set TORCH_EXTENSIONS_DIR to a writable folder")
    log.warning("torch extensions cache %s not writable (%s): building the compiled rasterizer in %s", default,
                problem, fallback)
    os.environ["TORCH_EXTENSIONS_DIR"] = str(fallback)


@contextlib.contextmanager
def one_builder(name: str) -> Iterator[Path]:
    """The extension's build folder, held by one process at a time.

    torch's own build lock is a file that exists while a process builds (``FileBaton``): a builder killed mid-build
    leaves it behind, and every later process then waits on it forever (seen when a test run was stopped during a
    build). An OS lock ends with the process that holds it, so under it a baton left behind can only be a dead
    builder's, and is removed."""
    from torch.utils.cpp_extension import (
        _get_build_directory,  # torch's rule for the folder, not a copy of it
    )

    build_directory = Path(_get_build_directory(name, verbose=False))
    with open(build_directory / "tracegs.flock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        try:
            (build_directory / "lock").unlink(missing_ok=True)
            yield build_directory
        finally:
            fcntl.flock(held, fcntl.LOCK_UN)


@functools.cache
def library() -> ctypes.CDLL:
    """The compiled library (rasterizer and preprocessing), built at first use."""
    from torch.utils.cpp_extension import load

    _ninja_on_path()
    writable_extension_cache()
    key = hashlib.sha256(b"".join(source.read_bytes() for source in SOURCES) + torch.__version__.encode()
                         + torch.__file__.encode() + " ".join(COMPILE_FLAGS).encode()).hexdigest()[:16]
    # torch warns in a box of many lines about a compiler other than the one it was built with; where the build
    # fails, compiled_unavailable() names the compiler's own complaint in one line instead.
    torch_log = logging.getLogger("torch.utils.cpp_extension")
    level = torch_log.level
    torch_log.setLevel(logging.ERROR)
    name = f"tracegs_rasterize_{key}"
    try:
        with one_builder(name) as build_directory:
            path = load(name, [str(source) for source in SOURCES], extra_cflags=COMPILE_FLAGS,
                        build_directory=str(build_directory), is_python_module=False)
    finally:
        torch_log.setLevel(level)
    compiled = ctypes.CDLL(path)
    int64, floats = ctypes.c_int64, [_float_p]
    compiled.rasterize_forward.restype = ctypes.c_int
    compiled.rasterize_forward.argtypes = ([int64, _int64_p] + [int64] * 3 + [ctypes.c_int, ctypes.c_float]
                                           + floats * 7 + [_int64_p])
    compiled.rasterize_backward.restype = ctypes.c_int
    compiled.rasterize_backward.argtypes = ([int64, _int64_p] + [int64] * 3 + [ctypes.c_int] + floats * 6 + [_int64_p]
                                            + floats * 6)
    compiled.preprocess_forward.restype = int64
    compiled.preprocess_forward.argtypes = [int64, ctypes.c_int, int64, int64] + floats * 12 + [
        ctypes.POINTER(ctypes.c_int32), ctypes.POINTER(ctypes.c_bool), _int64_p]
    compiled.preprocess_backward.restype = None
    compiled.preprocess_backward.argtypes = [int64, ctypes.c_int, int64, int64] + floats * 15
    return compiled


@functools.cache
def compiled_unavailable() -> str | None:
    """Why the compiled library cannot be built or loaded here, or None when it is (compiled once per machine,
    then cached): the first line of a failed build's output where the compiler or the shell complains (ninja's
    output is mostly the commands it ran), else the error's last line."""
    try:
        library()
    except Exception as error:  # no compiler, no ninja, a failed build
        if out_of_memory(error):  # no property of the machine's tools: the entry point says it as such
            raise
        lines = [line.strip() for line in str(error).strip().splitlines()[1:]]
        said = next((line for line in lines if re.search(r"error|not found", line, re.IGNORECASE)),
                    lines[-1] if lines else one_line(error))
        return f"{type(error).__name__}: {said}"
    return None


_POINTER_TYPES = {torch.float32: _float_p, torch.int64: _int64_p, torch.int32: ctypes.POINTER(ctypes.c_int32),
                  torch.bool: ctypes.POINTER(ctypes.c_bool)}


def pointer(tensor: Tensor):
    """The C pointer to a contiguous CPU tensor's data."""
    return ctypes.cast(tensor.data_ptr(), _POINTER_TYPES[tensor.dtype])


class _CompiledComposite(torch.autograd.Function):
    """Forward and backward of the compiled kernel; the gradient formulas are those of `rasterize._TileComposite`
    written per pixel (see the C++ source)."""

    @staticmethod
    def forward(ctx, means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                order: Tensor, width: int, height: int, tile_size: int) -> tuple[Tensor, Tensor]:
        inputs = [x.detach().to(torch.float32).contiguous() for x in (means2d, conics, opacities, features, extents)]
        order = order.contiguous()
        channels = features.shape[-1]
        out = inputs[0].new_empty(height, width, channels)
        final = inputs[0].new_empty(height, width)
        stop = torch.empty(height, width, dtype=torch.int64)
        library().rasterize_forward(order.shape[0], pointer(order), channels, width, height, tile_size, OCCLUSION_EPS,
                                    *map(pointer, inputs), pointer(out), pointer(final), pointer(stop))
        ctx.size = (width, height, tile_size)
        ctx.dtypes = [x.dtype for x in (means2d, conics, opacities, features)]
        ctx.save_for_backward(*inputs, order, final, stop)
        return out.to(features.dtype), final.to(features.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor, grad_final: Tensor):
        *inputs, order, final, stop = ctx.saved_tensors
        width, height, tile_size = ctx.size
        grad_out = grad_out.to(torch.float32).contiguous()
        grad_final = grad_final.to(torch.float32).contiguous()
        grads = [torch.zeros_like(x) for x in inputs[:4]]
        library().rasterize_backward(order.shape[0], pointer(order), inputs[3].shape[-1], width, height, tile_size,
                                     *map(pointer, inputs), pointer(final), pointer(stop), pointer(grad_out),
                                     pointer(grad_final), *map(pointer, grads))
        return (*(grad.to(dtype) for grad, dtype in zip(grads, ctx.dtypes)), None, None, None, None, None)


def rasterize_compiled(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                       width: int, height: int, tile_size: int = 4, order: Tensor | None = None
                       ) -> tuple[Tensor, Tensor]:
    """`rasterize_tiles` compiled; returns ([H,W,C], [H,W]). The splats are the rows `order` (int64, front to back)
    of the inputs, all rows in their given order when None; the others get zero gradient. `means2d` may carry
    a leading camera axis of size 1 ([1,N,2], as `render` keeps it)."""
    if means2d.device.type != "cpu":
        raise ValueError(f"the compiled rasterizer runs on the CPU, got tensors on {means2d.device}")
    if tile_size not in TILE_SIZES:
        raise ValueError(f"the compiled rasterizer supports tile sizes {TILE_SIZES}, got {tile_size}")
    if order is None:
        order = torch.arange(features.shape[0])
    return _CompiledComposite.apply(means2d, conics, opacities, features, extents, order, width, height, tile_size)
