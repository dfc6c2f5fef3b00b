"""A quick look at the newest raw for the dashboard: cheap enough to run once per frame.

LibRaw's half-size develop skips demosaicing (each 2x2 Bayer cell becomes one pixel), uses the
camera's as-shot white balance and sRGB gamma; the result is shrunk and sent as a small JPEG. It is
a preview for the operator's eye, not the process stage's calibrated develop.
"""

from __future__ import annotations

import functools
import io
from pathlib import Path

import rawpy
from PIL import Image

from station.errors import BadInputError

PREVIEW_WIDTH = 480


def raw_preview_jpeg(path: Path, max_width: int = PREVIEW_WIDTH) -> bytes:
    """The raw at `path` as a JPEG at most `max_width` pixels wide (newest frames are cached)."""
    try:
        stat = Path(path).stat()
    except OSError as exc:
        raise BadInputError(f"{path}: no preview, the raw cannot be read ({exc})") from exc
    return _preview(str(path), stat.st_mtime_ns, stat.st_size, max_width)


@functools.lru_cache(maxsize=8)
def _preview(path: str, mtime_ns: int, size: int, max_width: int) -> bytes:
    """Keyed on the file's mtime and size too: a re-shot frame replaces its raw under the same name."""
    try:
        with rawpy.imread(path) as raw:
            rgb = raw.postprocess(half_size=True, use_camera_wb=True, output_bps=8)  # [H/2, W/2, 3] uint8
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise BadInputError(f"{path}: no preview, LibRaw cannot read it ({type(exc).__name__}: {exc})") from exc
    image = Image.fromarray(rgb)
    image.thumbnail((max_width, max_width))
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", quality=85)
    return buffer.getvalue()
