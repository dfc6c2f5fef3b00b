"""Image files from untrusted folders: the size is read from the header and checked before decoding.

A 2.6 MB PNG may claim 30000x30000 pixels; decoding it and converting to float32 takes many GB.
`ImageLimits` bounds what a reader will decode; every image reader of the station asks `checked_size`
first, then decodes, and turns a truncated or unreadable file into a FormatError naming it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from station.errors import FormatError, InputTooLargeError


@dataclass(frozen=True)
class ImageLimits:
    """The largest image a reader decodes; raise `max_pixels` for a sensor beyond 100 megapixels."""

    max_pixels: int = 100_000_000
    max_side: int = 65_536


DEFAULT_LIMITS = ImageLimits()


def checked_size(path: Path, field: str | None = None, limits: ImageLimits = DEFAULT_LIMITS) -> tuple[int, int]:
    """(width, height) from the file's header alone, refused if empty, unreadable or over the limits."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, field, "missing")
    if path.stat().st_size == 0:
        raise FormatError(path, field, "empty file (0 bytes)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our own limit decides below
            with Image.open(path) as img:  # reads the header only
                width, height = img.size
    except Image.DecompressionBombError as exc:  # Pillow's own cap, twice Image.MAX_IMAGE_PIXELS
        raise InputTooLargeError(path, field, f"header claims too many pixels ({exc})") from exc
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise FormatError(path, field, f"not a readable image ({exc})") from exc
    if width < 1 or height < 1 or max(width, height) > limits.max_side or width * height > limits.max_pixels:
        raise InputTooLargeError(path, field, f"header says {width}x{height} pixels, beyond the limit of "
                                              f"{limits.max_pixels} pixels and {limits.max_side} a side")
    return width, height


def open_pil(path: Path, field: str | None = None, limits: ImageLimits = DEFAULT_LIMITS) -> Image.Image:
    """The decoded PIL image (pixels loaded), after the header check; truncated data is a FormatError."""
    checked_size(path, field, limits)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            img = Image.open(path)
            img.load()
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise FormatError(path, field, f"truncated or corrupt image ({exc})") from exc
    return img


def read_cv2(path: Path, field: str | None = None, limits: ImageLimits = DEFAULT_LIMITS) -> np.ndarray:
    """cv2.imread(IMREAD_UNCHANGED) after the header check; None from OpenCV becomes a FormatError."""
    width, height = checked_size(path, field, limits)
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.shape[:2] != (height, width):
        raise FormatError(path, field, "truncated or corrupt image (OpenCV could not decode it)")
    return data
