"""Image files the process stage writes: 16-bit sRGB PNG, half-float linear EXR, 8-bit masks.

Training wants display-referred sRGB at 16 bits (no banding in dark stones); anyone doing
radiometry wants scene-linear values, so those go to EXR as half floats (pipeline.md). Every
write goes through `atomic_write_with`, so a killed process never leaves half an image.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import OpenEXR

from station.errors import BadInputError, FormatError, InputTooLargeError
from station.formats.images import DEFAULT_LIMITS, ImageLimits, read_cv2
from station.scanfolder import atomic_write_with


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function; input clipped to [0, 1] first."""
    x = np.clip(linear, 0.0, 1.0).astype(np.float32)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    x = np.clip(encoded, 0.0, 1.0).astype(np.float32)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def _check_rgb(image: np.ndarray, path: Path) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise BadInputError(f"{path}: expected an [H, W, 3] image, got shape {image.shape}")
    if not np.all(np.isfinite(image)):
        raise BadInputError(f"{path}: image holds NaN or inf values")


def write_png16(path: Path, linear_rgb: np.ndarray) -> None:
    """Encode scene-linear RGB [H, W, 3] (1.0 = white) as 16-bit sRGB PNG."""
    _check_rgb(linear_rgb, path)
    encoded = np.round(linear_to_srgb(linear_rgb) * 65535.0).astype(np.uint16)  # [H, W, 3]
    _write_png(path, np.ascontiguousarray(encoded[:, :, ::-1]), "PNG")


def read_png16(path: Path) -> np.ndarray:
    """Read a PNG written by `write_png16` back to linear float32 RGB [H, W, 3]."""
    data = read_cv2(path)
    if data.ndim != 3 or data.shape[2] != 3:
        raise FormatError(path, None, f"not a 3-channel PNG (shape {data.shape})")
    scale = 65535.0 if data.dtype == np.uint16 else 255.0
    return srgb_to_linear(data[:, :, ::-1].astype(np.float32) / scale)


def write_mask_png(path: Path, mask: np.ndarray) -> None:
    """Masks are 8-bit single-channel PNGs, the form nerfstudio and COLMAP read: 255 is stone, 0 is not,
    and a value between is a coverage (`bool` masks, and readers that threshold at 128, see 0/255)."""
    if mask.ndim != 2:
        raise BadInputError(f"{path}: expected an [H, W] mask, got shape {mask.shape}")
    _write_png(path, np.rint(np.clip(mask.astype(np.float32), 0.0, 1.0) * 255).astype(np.uint8), "mask PNG")


def _write_png(path: Path, data: np.ndarray, what: str) -> None:
    """Atomic PNG write of BGR or single-channel `data` through OpenCV."""

    def writer(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), data):
            raise OSError(f"{path}: OpenCV could not write the {what}")

    atomic_write_with(path, writer)


def read_mask_png(path: Path) -> np.ndarray:
    data = read_cv2(path)
    if data.ndim == 3:
        data = data[:, :, -1] if data.shape[2] == 4 else data[:, :, 0]
    return data > 127


def write_exr_half(path: Path, linear_rgb: np.ndarray) -> None:
    """Linear RGB as one half-float "RGB" channel group (OpenEXR 3.x File API)."""
    _check_rgb(linear_rgb, path)
    pixels = np.ascontiguousarray(linear_rgb.astype(np.float16))  # [H, W, 3]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def writer(tmp: Path) -> None:
        with OpenEXR.File(header, {"RGB": pixels}) as out:
            out.write(str(tmp))

    atomic_write_with(path, writer)


def read_exr(path: Path, limits: ImageLimits = DEFAULT_LIMITS) -> np.ndarray:
    """Read the RGB channels of an EXR as float32 [H, W, 3], its size checked from the header first."""
    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            (x0, y0), (x1, y1) = exr.header()["dataWindow"]
        if (x1 - x0 + 1) * (y1 - y0 + 1) > limits.max_pixels:
            raise InputTooLargeError(path, None, f"header says {x1 - x0 + 1}x{y1 - y0 + 1} pixels, "
                                                 f"beyond the limit of {limits.max_pixels}")
        with OpenEXR.File(str(path)) as exr:
            channels = exr.channels()
            if "RGB" in channels:
                pixels = np.array(channels["RGB"].pixels)
            else:
                pixels = np.stack([np.array(channels[c].pixels) for c in "RGB"], axis=-1)
    except (OSError, RuntimeError, KeyError) as exc:
        raise FormatError(path, None, f"not a readable RGB OpenEXR file ({exc})") from exc
    return pixels.astype(np.float32)
