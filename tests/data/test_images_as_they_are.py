"""Images as a camera or an editor wrote them: every supported PIL mode reads as its 8-bit RGB version would,
other modes and images whose size disagrees with their camera are refused naming the file."""

from __future__ import annotations

import logging
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scene_builders import write_scene

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.errors import InputFileError


def source(root: Path) -> SceneSourceConfig:
    return SceneSourceConfig(root=str(root), preset="custom", normalize=False)


def write_png16(path: Path, pixels: np.ndarray) -> None:
    """A 16-bit PNG (gray, RGB or RGBA by the last axis) written byte by byte: PIL cannot write 16-bit colour."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    rows = b"".join(b"\x00" + pixels[y].astype(">u2").tobytes() for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 16, {1: 0, 3: 2, 4: 6}[channels], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
                     + chunk(b"IEND", b""))


def rewrite(path: Path, mode: str) -> np.ndarray:
    """Re-save the scene's image at ``path`` in ``mode``; returns the 8-bit RGB image it should read as."""
    rgb = np.asarray(Image.open(path).convert("RGB"))
    if mode == "I;16":  # 16-bit gray from the 8-bit gray: v16 = 257 v8 is the same brightness
        gray = np.asarray(Image.fromarray(rgb).convert("L"))
        Image.fromarray(gray.astype(np.uint16) * 257).save(path)
        return np.repeat(gray[..., None], 3, axis=2)
    if mode == "RGB;16":
        write_png16(path, rgb.astype(np.uint16) * 257)
        return rgb
    if mode == "RGBA;16":
        write_png16(path, np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], 2).astype(np.uint16)
                    * 257)
        return rgb
    image = Image.fromarray(rgb).convert(mode)
    image.save(path.with_suffix(".tiff") if mode == "CMYK" else path, format="TIFF" if mode == "CMYK" else "PNG")
    if mode == "CMYK":
        path.with_suffix(".tiff").replace(path)
    return np.asarray(image.convert("RGB"))


MODES = ["L", "LA", "P", "RGBA", "CMYK", "1", "I;16", "RGB;16", "RGBA;16"]


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_reads_as_its_8_bit_rgb_version(tmp_path, mode):
    root, _ = write_scene(tmp_path / "s" / "ring", n=4)
    path = root / "images" / "img_001.png"
    expected = rewrite(path, mode)
    image = load_scene(source(root.parent), root.name).load_image(1)
    assert image.shape == (3, 24, 36) and image.dtype == torch.float32
    difference = (image.permute(1, 2, 0).numpy() - expected / 255.0).__abs__().max()
    assert difference <= 1 / 255 + 1e-6, (mode, difference)


def test_16_bit_gray_png_is_its_8_bit_version_within_one_level(tmp_path):
    root, _ = write_scene(tmp_path / "s" / "ring", n=4)
    eight, sixteen = root / "images" / "img_001.png", root / "images" / "img_002.png"
    gray = np.random.default_rng(1).integers(0, 256, (24, 36), dtype=np.uint16)
    Image.fromarray(gray.astype(np.uint8)).save(eight)
    # What a 16-bit sensor records for those 8-bit levels: 257 v8, plus up to half a level of finer detail.
    detail = np.random.default_rng(2).integers(0, 128, gray.shape)
    Image.fromarray(np.minimum(gray * 257 + detail, 65535).astype(np.uint16)).save(sixteen)
    assert Image.open(sixteen).mode == "I;16"
    scene = load_scene(source(root.parent), root.name)
    assert (scene.load_image(2) - scene.load_image(1)).abs().max() <= 1 / 255
    assert abs(float(scene.load_image(2).mean()) - float(gray.mean()) / 255) < 0.01  # not saturated white


def test_exif_orientation_is_applied(tmp_path):
    root, _ = write_scene(tmp_path / "s" / "ring", n=4)
    path = root / "images" / "img_001.png"
    upright = np.asarray(Image.open(path).convert("RGB"))
    exif = Image.Exif()
    exif[0x0112] = 3  # stored upside down; viewers rotate it by 180 degrees
    Image.fromarray(upright[::-1, ::-1].copy()).save(path, exif=exif)
    image = load_scene(source(root.parent), root.name).load_image(1)
    assert torch.allclose(image.permute(1, 2, 0), torch.from_numpy(upright / 255.0).float(), atol=1e-6)


@pytest.mark.parametrize("case", ["float_tiff", "transparent", "rotated_by_exif", "other_aspect"])
def test_unusable_image_is_refused_naming_it(tmp_path, case):
    root, _ = write_scene(tmp_path / "s" / "ring", n=4)
    path = root / "images" / "img_002.png"
    rgb = np.asarray(Image.open(path).convert("RGB"))
    if case == "float_tiff":
        Image.fromarray(rgb[..., 0].astype(np.float32) / 255.0, mode="F").save(path, format="TIFF")
        expected = f"{path}: unsupported image mode F"
    elif case == "transparent":
        alpha = np.full(rgb.shape[:2] + (1,), 255, np.uint8)
        alpha[0, 0] = 0
        Image.fromarray(np.concatenate([rgb, alpha], 2)).save(path)
        expected = f"{path}: mode RGBA with transparent pixels (1 of 864)"
    elif case == "rotated_by_exif":
        exif = Image.Exif()
        exif[0x0112] = 6  # a portrait shot: upright it is 24 wide and 36 high
        Image.fromarray(rgb).save(path, exif=exif)
        expected = f"{path}: image is 24x36 but its camera in {root / 'sparse' / '0'} is 36x24"
    else:
        Image.fromarray(rgb).resize((30, 30)).save(path)
        expected = f"{path}: image is 30x30 but its camera in {root / 'sparse' / '0'} is 36x24 (another aspect"
    with pytest.raises(InputFileError) as error:
        load_scene(source(root.parent), root.name)
    assert str(error.value).startswith(expected), str(error.value)


def test_image_of_the_same_aspect_ratio_scales_the_intrinsics_and_says_so(tmp_path, caplog):
    root, cameras = write_scene(tmp_path / "s" / "ring", n=4)
    path = root / "images" / "img_002.png"
    Image.open(path).resize((18, 12)).save(path)
    with caplog.at_level(logging.INFO, logger="tracegs.data.colmap"):
        scene = load_scene(source(root.parent), root.name)
    assert (scene.cameras[2].width, scene.cameras[2].height) == (18, 12)
    torch.testing.assert_close(scene.cameras[2].K[:2], cameras[2].K[:2] / 2, atol=1e-5, rtol=0)
    assert "images of 18x12 with cameras of 36x24" in caplog.text and "intrinsics scaled" in caplog.text
