"""A minimal DNG writer for the simulated camera, and a LibRaw-backed reader for checking it.

Only the tags LibRaw needs to decode a Bayer mosaic bit-exactly are written (docs: rig.md, "Raw files
LibRaw really reads"). LibRaw fails silently without CFAPattern or BlackLevel (pattern [[6]],
black 0), so `read_dng` refuses files that decode that way.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import rawpy
import tifffile

from sim.sensor import SensorModel
from station.errors import BadInputError

# TIFF field types (TIFF 6.0 section 2): 1 BYTE, 2 ASCII, 3 SHORT, 4 LONG, 5 RATIONAL, 10 SRATIONAL
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL = 1, 2, 3, 4, 5, 10
_RGGB = (0, 1, 1, 2)  # CFAPattern colour codes: 0 red, 1 green, 2 blue


def _rationals(values: np.ndarray, denominator: int = 10000) -> list[int]:
    """Flat (numerator, denominator) pairs, as tifffile wants RATIONAL/SRATIONAL values."""
    pairs: list[int] = []
    for value in np.asarray(values, dtype=float).ravel():
        frac = Fraction(float(value)).limit_denominator(denominator)
        pairs += [frac.numerator, frac.denominator]
    return pairs


def dng_bytes(mosaic_u16: np.ndarray, sensor: SensorModel, camera_model: str = "station-sim") -> bytes:
    """Encode an RGGB mosaic [H, W] uint16 as a DNG 1.4 file that LibRaw decodes bit-exactly."""
    if mosaic_u16.dtype != np.uint16 or mosaic_u16.ndim != 2:
        raise BadInputError(f"mosaic must be a 2-D uint16 array, got {mosaic_u16.dtype} {mosaic_u16.shape}")
    if not camera_model.isascii() or not camera_model:
        raise BadInputError(f"camera model {camera_model!r} must be non-empty ASCII")
    extratags = [
        (33421, _SHORT, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, _BYTE, 4, _RGGB, True),  # CFAPattern
        (50706, _BYTE, 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, _ASCII, 0, camera_model, True),  # UniqueCameraModel
        (50714, _LONG, 1, int(sensor.black_level), True),  # BlackLevel
        (50717, _LONG, 1, int(sensor.white_level), True),  # WhiteLevel
        (50721, _SRATIONAL, 9, _rationals(sensor.xyz_to_camera), True),  # ColorMatrix1, XYZ -> camera
        (50728, _RATIONAL, 3, _rationals(sensor.camera_neutral()), True),  # AsShotNeutral
        (50778, _SHORT, 1, 21, True),  # CalibrationIlluminant1 = D65
    ]
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, np.ascontiguousarray(mosaic_u16), photometric=32803, subfiletype=0, extratags=extratags, metadata=None
    )
    return buffer.getvalue()


@dataclass
class DngInfo:
    """What LibRaw made of a raw file."""

    raw_image: np.ndarray  # [H, W] uint16
    raw_pattern: np.ndarray  # [2, 2] colour indices, 0 R, 1 G, 2 B, 3 second G
    black_level: int
    white_level: int
    camera_whitebalance: np.ndarray  # [4] multipliers LibRaw reports (1 / AsShotNeutral, scaled)
    color_matrix: np.ndarray  # [3, 4] as LibRaw reports it


def read_dng(data: bytes, source: str = "<bytes>") -> DngInfo:
    """Decode raw bytes with LibRaw and refuse the silent failures (no CFA pattern, zero black)."""
    try:
        with rawpy.imread(io.BytesIO(data)) as raw:
            info = DngInfo(
                raw_image=raw.raw_image.copy(),
                raw_pattern=np.array(raw.raw_pattern),
                black_level=int(raw.black_level_per_channel[0]),
                white_level=int(raw.white_level),
                camera_whitebalance=np.array(raw.camera_whitebalance, dtype=float),
                color_matrix=np.array(raw.color_matrix, dtype=float),
            )
    except (rawpy.LibRawError, ValueError) as exc:
        raise BadInputError(f"{source}: LibRaw cannot decode it ({exc})") from exc
    if info.raw_pattern.shape != (2, 2) or info.raw_pattern.max() > 3:
        raise BadInputError(f"{source}: no usable CFA pattern (LibRaw reports {info.raw_pattern.tolist()})")
    if info.black_level == 0:
        raise BadInputError(f"{source}: black level decoded as 0 (BlackLevel tag missing?)")
    return info
