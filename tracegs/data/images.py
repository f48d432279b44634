"""Captured images as float RGB in [0, 1], whatever PIL mode a camera or an editor wrote them in.

``Image.convert("RGB")`` is right for 8-bit modes but clips 16-bit gray (``I;16``) at 255 instead of
scaling it, so a 16-bit gray photograph would read as nearly white. Here each mode is decoded by its own
rule, so every supported mode gives what its 8-bit RGB version would (16-bit values keep their extra
precision); anything else is refused naming the file and the mode. The EXIF orientation tag is applied, as
every image viewer does, so the pixels are the upright photograph the camera's pose was solved for.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps

from tracegs.errors import InputFileError, one_line

EIGHT_BIT_MODES = ("1", "L", "P", "RGB", "CMYK", "YCbCr")  # PIL converts these to RGB exactly
ALPHA_MODES = ("LA", "La", "PA", "RGBA", "RGBa")  # colour plus alpha: usable when fully opaque
SIXTEEN_BIT_GRAY = ("I;16", "I;16L", "I;16B", "I;16N")
SUPPORTED = (*EIGHT_BIT_MODES, *ALPHA_MODES, *SIXTEEN_BIT_GRAY, "I")


def _decode(pil: Image.Image, path: Path) -> np.ndarray:
    """float32 [H, W, 3] in [0, 1] from a loaded, upright image of any supported mode."""
    mode = pil.mode
    if mode in SIXTEEN_BIT_GRAY or (mode == "I" and pil.format == "PNG"):  # PNG's 16-bit gray opens as "I"
        gray = np.asarray(pil).astype(np.float32) / 65535.0
        return np.repeat(gray[..., None], 3, axis=2)
    if mode == "P" and "transparency" in pil.info:
        pil, mode = pil.convert("RGBA"), "RGBA"
    if mode in ALPHA_MODES:
        alpha = np.asarray(pil.getchannel("A"))
        if alpha.min() < 255:
            raise InputFileError(path, f"mode {mode} with transparent pixels ({int((alpha < 255).sum())} of "
                                       f"{alpha.size}); a 3DGS fit needs every pixel's colour",
                                 "flatten it onto the background it was captured against and save it as RGB")
    elif mode not in EIGHT_BIT_MODES:
        raise InputFileError(path, f"unsupported image mode {mode}; supported: {', '.join(SUPPORTED)}",
                             "save it as 8- or 16-bit gray or RGB (PNG or JPEG)")
    return np.asarray(pil.convert("RGB"), dtype=np.float32) / 255.0


def read_rgb(path: str | Path) -> np.ndarray:
    """The image at ``path`` as float32 [H, W, 3] in [0, 1], upright; a file PIL cannot decode or of a mode
    with no RGB reading raises :class:`InputFileError` naming it."""
    path = Path(path)
    try:
        with Image.open(path) as pil:
            pil.load()
            return _decode(ImageOps.exif_transpose(pil), path)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:  # PIL's decode errors
        raise InputFileError(path, f"cannot decode the image ({one_line(error)})",
                             "replace it with an intact copy or remove it from the COLMAP model") from error


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """A float [H, W, 3] image resampled to ``width`` x ``height`` (Lanczos, each channel in float, so 16-bit
    precision survives), clipped back to [0, 1] (Lanczos overshoots at edges)."""
    channels = [np.asarray(Image.fromarray(image[..., c], mode="F").resize((width, height), Image.Resampling.LANCZOS))
                for c in range(image.shape[2])]
    return np.clip(np.stack(channels, axis=2), 0.0, 1.0)


def to_uint8(frames: torch.Tensor) -> torch.Tensor:
    """Float pixels in [0, 1] (any shape) as 8-bit values: clamped and rounded, never a raw cast (which would
    truncate 0.999 to 254)."""
    return (frames.clamp(0, 1) * 255.0).round().to(torch.uint8)
