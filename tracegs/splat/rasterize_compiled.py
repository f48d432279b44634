"""The tile rasterizer of `rasterize.py` compiled to C++, forward and backward (CPU, float32).

Same inputs, tiles, depth order, 1/255 alpha threshold, 0.99 alpha clamp and transmittance cut-off as
`rasterize_tiles`; projection and SH stay in PyTorch autograd, only the compositing is compiled
(`rasterize_compiled.cpp`). The pure-PyTorch backend spends most of its time on the fixed overhead of many small
tensor operations; the compiled loop walks each tile's splats once, updates the tile's pixels in SIMD registers,
stops when the tile is opaque and needs no intermediate tensors, which makes the compositing more than ten
times faster (the projection and SH in PyTorch then take about half of a render's forward and backward).

Why this tool: `torch.utils.cpp_extension.load` compiles at first use with the C++ compiler and ninja (a
declared dependency) into the torch extensions cache (``~/.cache/torch_extensions``, or
``$TORCH_EXTENSIONS_DIR``), guards the build with a lock file so concurrent processes (forked workers, parallel
pytest) build once and the others wait, and reuses the library afterwards. It is not built at install time
because pip's build isolation would pull a CUDA torch. The source includes no torch headers and exposes a plain C
ABI called through ctypes: with ``torch/extension.h`` and pybind11 the one-time compile takes ~45 s on a 2-core
machine, without them ~2 s. numba was the alternative; it is not a dependency here and would JIT-compile in every
fresh worker process. The build directory is named by a hash of the source and of the torch installation, so
checkouts or venvs with different sources never rebuild a library another process has loaded.

The kernel is single-threaded: the embedded pipeline already runs one single-threaded fit per core. It is
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

SOURCE = Path(__file__).with_name("rasterize_compiled.cpp")
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
def _library() -> ctypes.CDLL:
    from torch.utils.cpp_extension import load

    _ninja_on_path()
    key = hashlib.sha256(SOURCE.read_bytes() + torch.__version__.encode() + torch.__file__.encode()
                         + " ".join(COMPILE_FLAGS).encode()).hexdigest()[:16]
    path = load(f"tracegs_rasterize_{key}", [str(SOURCE)], extra_cflags=COMPILE_FLAGS, is_python_module=False)
    library = ctypes.CDLL(path)
    library.rasterize_forward.restype = ctypes.c_int
    library.rasterize_forward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_int, ctypes.c_float] + [_float_p] * 7 + [
        _int64_p]
    library.rasterize_backward.restype = ctypes.c_int
    library.rasterize_backward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_int] + [_float_p] * 6 + [_int64_p] + [
        _float_p] * 6
    return library


@functools.cache
def compiled_available() -> bool:
    """Whether the compiled rasterizer builds and loads here (compiled once per machine, then cached)."""
    try:
        _library()
    except Exception as error:  # no compiler, no ninja, a failed build: the torch backend still works
        log.warning("compiled rasterizer unavailable (%s: %s); using the pure-PyTorch rasterizer",
                    type(error).__name__, str(error).strip().splitlines()[-1] if str(error).strip() else "")
        return False
    return True


def _pointer(tensor: Tensor, kind=_float_p):
    return ctypes.cast(tensor.data_ptr(), kind)


class _CompiledComposite(torch.autograd.Function):
    """Forward and backward of the compiled kernel; the gradient formulas are those of `rasterize._TileComposite`
    written per pixel (see the C++ source)."""

    @staticmethod
    def forward(ctx, means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                width: int, height: int, tile_size: int) -> tuple[Tensor, Tensor]:
        inputs = [x.detach().to(torch.float32).contiguous() for x in (means2d, conics, opacities, features, extents)]
        count, channels = features.shape
        out = inputs[0].new_empty(height, width, channels)
        final = inputs[0].new_empty(height, width)
        stop = torch.empty(height, width, dtype=torch.int64)
        _library().rasterize_forward(count, channels, width, height, tile_size, OCCLUSION_EPS,
                                     *map(_pointer, inputs), _pointer(out), _pointer(final), _pointer(stop, _int64_p))
        ctx.size = (width, height, tile_size)
        ctx.dtypes = [x.dtype for x in (means2d, conics, opacities, features)]
        ctx.save_for_backward(*inputs, final, stop)
        return out.to(features.dtype), final.to(features.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor, grad_final: Tensor):
        *inputs, final, stop = ctx.saved_tensors
        width, height, tile_size = ctx.size
        grad_out = grad_out.to(torch.float32).contiguous()
        grad_final = grad_final.to(torch.float32).contiguous()
        grads = [torch.zeros_like(x) for x in inputs[:4]]
        count, channels = inputs[3].shape
        _library().rasterize_backward(count, channels, width, height, tile_size, *map(_pointer, inputs),
                                      _pointer(final), _pointer(stop, _int64_p), _pointer(grad_out),
                                      _pointer(grad_final), *map(_pointer, grads))
        return (*(grad.to(dtype) for grad, dtype in zip(grads, ctx.dtypes)), None, None, None, None)


def rasterize_compiled(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, extents: Tensor,
                       width: int, height: int, tile_size: int = 4) -> tuple[Tensor, Tensor]:
    """`rasterize_tiles` compiled: inputs sorted front to back on the CPU; returns ([H,W,C], [H,W])."""
    if means2d.device.type != "cpu":
        raise ValueError(f"the compiled rasterizer runs on the CPU, got tensors on {means2d.device}")
    if tile_size not in TILE_SIZES:
        raise ValueError(f"the compiled rasterizer supports tile sizes {TILE_SIZES}, got {tile_size}")
    return _CompiledComposite.apply(means2d, conics, opacities, features, extents, width, height, tile_size)
