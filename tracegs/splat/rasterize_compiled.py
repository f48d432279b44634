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
loaded.

The kernels are single-threaded: the embedded pipeline already runs one single-threaded fit per core. It is
compiled for tiles of 4, 8 and 16 pixels (`TILE_SIZES`); `rasterize_tiles` uses 4.
Where no compiler is available, `compiled_available()` is False after one logged warning and the `auto`
backend falls back to the pure-PyTorch rasterizer.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import shutil
from pathlib import Path

import torch
from torch import Tensor

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


@functools.cache
def library() -> ctypes.CDLL:
    """The compiled library (rasterizer and preprocessing), built at first use."""
    from torch.utils.cpp_extension import load

    _ninja_on_path()
    key = hashlib.sha256(b"".join(source.read_bytes() for source in SOURCES) + torch.__version__.encode()
                         + torch.__file__.encode() + " ".join(COMPILE_FLAGS).encode()).hexdigest()[:16]
    path = load(f"tracegs_rasterize_{key}", [str(source) for source in SOURCES], extra_cflags=COMPILE_FLAGS,
                is_python_module=False)
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
def compiled_available() -> bool:
    """Whether the compiled rasterizer builds and loads here (compiled once per machine, then cached)."""
    try:
        library()
    except Exception as error:  # no compiler, no ninja, a failed build: the torch backend still works
        log.warning("compiled rasterizer unavailable (%s: %s); using the pure-PyTorch rasterizer",
                    type(error).__name__, str(error).strip().splitlines()[-1] if str(error).strip() else "")
        return False
    return True


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
