"""Linear, reproducible raw develop: any LibRaw raw, or a headerless Bayer dump.

Both paths end in the same place: white-balanced camera RGB scaled so 1.0 is the sensor's
white level, then one 3x3 matrix to linear sRGB, then an area-filtered downscale. LibRaw is
driven so that output stays proportional to exposure (rig.md: `adjust_maximum_thr=0`,
no auto-brightness, explicit white balance, unit gamma). Frames that are black or
saturated are not errors: they come back with `flags` naming the reason, so a scan-level
stage can report them and carry on; only unreadable files raise `BadInputError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import rawpy
import tifffile

from station.errors import BadInputError

OutputSpace = Literal["srgb", "camera"]
DemosaicName = Literal["AHD", "PPG", "VNG", "DCB", "DHT", "AAHD", "LINEAR"]
BayerPattern = Literal["RGGB", "BGGR", "GRBG", "GBRG"]
MatrixSource = Literal["file", "libraw_table", "none"]

# sRGB (D65) primaries -> XYZ, IEC 61966-2-1; used to turn LibRaw's XYZ->camera table into camera->sRGB.
XYZ_FROM_SRGB = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)


@dataclass(frozen=True)
class DevelopSettings:
    """How to develop. Defaults are the training setup: AHD, linear sRGB, no downscale."""

    demosaic: DemosaicName = "AHD"
    output_space: OutputSpace = "srgb"
    max_width: int | None = None  # downscale (area filter) so the width is at most this
    clip_level: float = 0.98  # raw value / white level at or above which a photosite counts as clipped
    clipped_flag_fraction: float = 0.01  # flag "highlights_clipped" above this fraction of clipped photosites
    saturated_fraction: float = 0.5  # flag "saturated" above this fraction
    black_level_p99: float = 0.01  # flag "black" when the 99th percentile signal is below this


@dataclass(frozen=True)
class WhiteBalance:
    """Per-channel multipliers for camera R, G, B (green = 1), and where they came from."""

    gains: tuple[float, float, float]
    source: str

    def __post_init__(self) -> None:
        if not all(np.isfinite(g) and g > 0 for g in self.gains):
            raise BadInputError(f"white balance from {self.source}: gains must be positive, got {self.gains}")


@dataclass(frozen=True)
class BayerSpec:
    """A headerless Bayer dump: every fact LibRaw would read from a header, given explicitly."""

    width: int
    height: int
    pattern: BayerPattern
    black_level: tuple[float, float, float, float]  # per photosite of the 2x2 tile, row-major
    white_level: float
    dtype: str = "<u2"


@dataclass
class Mosaic:
    """Raw photosites plus what is needed to interpret them."""

    data: np.ndarray  # [H, W] uint16
    pattern: np.ndarray  # [2, 2] channel index 0=R 1=G 2=B
    black_level: np.ndarray  # [2, 2] per photosite
    white_level: float
    source: Path


@dataclass
class Developed:
    """A developed frame. `linear` is scene-linear, 1.0 = sensor white after white balance."""

    linear: np.ndarray  # [H, W, 3] float32
    source: Path
    space: OutputSpace
    clipped_fraction: float
    signal_p99: float
    camera_to_srgb: np.ndarray  # [3, 3]
    matrix_source: MatrixSource
    white_balance: WhiteBalance
    flags: list[str] = field(default_factory=list)


def _raise_unreadable(path: Path, why: str) -> None:
    raise BadInputError(f"{path}: {why}")


def open_raw(path: Path) -> rawpy.RawPy:
    """Open with LibRaw and validate what LibRaw fails to complain about."""
    path = Path(path)
    if not path.is_file():
        _raise_unreadable(path, "raw file is missing")
    try:
        raw = rawpy.imread(str(path))
        raw.raw_image_visible  # forces unpack: truncated data fails here, not later
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise BadInputError(f"{path}: not a raw file LibRaw can read ({type(exc).__name__}: {exc})") from exc
    pattern = raw.raw_pattern
    if pattern is None or pattern.shape != (2, 2) or pattern.max() > 3:
        raw.close()
        _raise_unreadable(path, f"no usable 2x2 Bayer CFA pattern (LibRaw reports {pattern!r})")
    _validate_dng_tags(path, raw)
    return raw


def _validate_dng_tags(path: Path, raw: rawpy.RawPy) -> None:
    """A DNG without CFAPattern or BlackLevel develops silently wrong in LibRaw (rig.md)."""
    with open(path, "rb") as handle:
        if handle.read(4) not in (b"II*\x00", b"MM\x00*"):
            return
    try:
        with tifffile.TiffFile(path) as tif:
            tags = {tag.code for page in tif.pages for tag in page.tags.values()}
    except (tifffile.TiffFileError, ValueError, OSError) as exc:
        raw.close()
        raise BadInputError(f"{path}: corrupt TIFF/DNG structure ({exc})") from exc
    if 50706 not in tags:  # DNGVersion: a TIFF-based vendor raw, LibRaw's tables apply
        return
    missing = [name for code, name in ((33422, "CFAPattern"), (50714, "BlackLevel")) if code not in tags]
    if missing:
        raw.close()
        _raise_unreadable(path, f"DNG lacks {' and '.join(missing)}; LibRaw would develop it silently wrong")


def camera_matrix(raw: rawpy.RawPy) -> tuple[np.ndarray, MatrixSource]:
    """Camera RGB -> linear sRGB. DNGs carry it in `color_matrix`; vendor raws in LibRaw's table."""
    from_file = np.asarray(raw.color_matrix, dtype=np.float64)[:3, :3]
    if np.abs(from_file).sum() > 1e-6:
        return from_file, "file"
    xyz_to_cam = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3, :3]
    if np.abs(xyz_to_cam).sum() > 1e-6:
        cam_from_srgb = xyz_to_cam @ XYZ_FROM_SRGB
        cam_from_srgb /= cam_from_srgb.sum(axis=1, keepdims=True)  # white stays white (LibRaw does the same)
        return np.linalg.inv(cam_from_srgb), "libraw_table"
    return np.eye(3), "none"


def _tile(tile: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Repeat a [2, 2] per-photosite value over a mosaic of `shape` (odd sizes too)."""
    h, w = shape
    return np.tile(tile, (h // 2 + 1, w // 2 + 1))[:h, :w]


def _signal_stats(
    mosaic: np.ndarray, black: np.ndarray, white: float, settings: DevelopSettings
) -> tuple[float, float]:
    """(fraction of clipped photosites, 99th percentile of black-subtracted signal in [0, 1])."""
    tiled_black = _tile(black, mosaic.shape)  # [H, W]
    clipped = float(np.mean(mosaic >= settings.clip_level * white))
    sample = (mosaic[::3, ::3] - tiled_black[::3, ::3]) / np.maximum(white - tiled_black[::3, ::3], 1.0)
    return clipped, float(np.percentile(sample, 99))


def _flags(clipped: float, p99: float, settings: DevelopSettings) -> list[str]:
    flags = []
    if p99 < settings.black_level_p99:
        flags.append("black")
    if clipped > settings.saturated_fraction:
        flags.append("saturated")
    elif clipped > settings.clipped_flag_fraction:
        flags.append("highlights_clipped")
    return flags


def _finish(camera_rgb: np.ndarray, source: Path, matrix: np.ndarray, matrix_source: MatrixSource,
            wb: WhiteBalance, clipped: float, p99: float, settings: DevelopSettings) -> Developed:
    """Shared tail of both develop paths: matrix to sRGB (if asked), area downscale, flags."""
    out = camera_rgb  # [H, W, 3]
    if settings.output_space == "srgb":
        out = cv2.transform(np.ascontiguousarray(out, dtype=np.float32), matrix.astype(np.float32))  # per-pixel 3x3
    return Developed(
        linear=downscale_area(out.astype(np.float32), settings.max_width),
        source=source,
        space=settings.output_space,
        clipped_fraction=clipped,
        signal_p99=p99,
        camera_to_srgb=matrix,
        matrix_source=matrix_source,
        white_balance=wb,
        flags=_flags(clipped, p99, settings) + (["no_colour_matrix"] if matrix_source == "none" else []),
    )


def downscale_area(image: np.ndarray, max_width: int | None) -> np.ndarray:
    """Area-average downscale (cv2.INTER_AREA) so no aliasing of stone texture; never upscales."""
    h, w = image.shape[:2]
    if max_width is None or w <= max_width:
        return image
    size = (max_width, max(1, round(h * max_width / w)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def develop_raw(path: Path, settings: DevelopSettings, wb: WhiteBalance | None = None) -> Developed:
    """Develop any raw LibRaw reads. Without `wb`, the file's as-shot white balance is used."""
    path = Path(path)
    raw = open_raw(path)
    with raw:
        mosaic = raw.raw_image_visible.astype(np.float32)
        black = np.asarray(raw.black_level_per_channel, dtype=np.float32)[raw.raw_pattern]  # [2, 2]
        white = float(raw.white_level)
        clipped, p99 = _signal_stats(mosaic, black, white, settings)
        matrix, matrix_source = camera_matrix(raw)
        if wb is None:
            cam = np.asarray(raw.camera_whitebalance[:3], dtype=np.float64)
            if not np.all(cam > 0):
                cam = np.ones(3)
            wb = WhiteBalance((float(cam[0] / cam[1]), 1.0, float(cam[2] / cam[1])), source=f"{path.name} as shot")
        gains = np.asarray(wb.gains, dtype=np.float64)
        try:
            rgb16 = raw.postprocess(
                demosaic_algorithm=getattr(rawpy.DemosaicAlgorithm, settings.demosaic),
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                adjust_maximum_thr=0.0,
                output_color=rawpy.ColorSpace.raw,
                user_wb=[float(gains[0]), float(gains[1]), float(gains[2]), float(gains[1])],
                user_flip=0,
            )
        except rawpy.LibRawError as exc:
            raise BadInputError(f"{path}: LibRaw failed to develop it ({type(exc).__name__}: {exc})") from exc
    # LibRaw scales so the smallest multiplier maps white to 65535; undo that to get 1.0 = white x gain.
    camera_rgb = rgb16.astype(np.float32) * np.float32(gains.min() / 65535.0)  # [H, W, 3]
    return _finish(camera_rgb, path, matrix, matrix_source, wb, clipped, p99, settings)


_PATTERN_INDEX = {
    "RGGB": [[0, 1], [1, 2]],
    "BGGR": [[2, 1], [1, 0]],
    "GRBG": [[1, 0], [2, 1]],
    "GBRG": [[1, 2], [0, 1]],
}
# OpenCV names Bayer codes after the second row's 2nd/3rd pixels, i.e. one diagonal step off the
# top-left tile: an RGGB sensor is COLOR_BayerBG2RGB. Checked by a round-trip test.
_CV_CODE = {
    "RGGB": cv2.COLOR_BayerBG2RGB_EA,
    "BGGR": cv2.COLOR_BayerRG2RGB_EA,
    "GRBG": cv2.COLOR_BayerGB2RGB_EA,
    "GBRG": cv2.COLOR_BayerGR2RGB_EA,
}


def load_bayer(path: Path, spec: BayerSpec) -> Mosaic:
    """Read a headerless Bayer dump; the size must match exactly, or the file is refused."""
    path = Path(path)
    if not path.is_file():
        _raise_unreadable(path, "raw file is missing")
    expected = spec.width * spec.height * np.dtype(spec.dtype).itemsize
    size = path.stat().st_size
    if size != expected:
        _raise_unreadable(path, f"{size} bytes, but {spec.width}x{spec.height} {spec.dtype} needs {expected}")
    data = np.fromfile(path, dtype=spec.dtype).reshape(spec.height, spec.width).astype(np.uint16)
    if data.max() > spec.white_level:
        _raise_unreadable(path, f"values up to {data.max()} exceed the stated white level {spec.white_level}")
    return Mosaic(
        data=data,
        pattern=np.array(_PATTERN_INDEX[spec.pattern]),
        black_level=np.asarray(spec.black_level, dtype=np.float32).reshape(2, 2),
        white_level=float(spec.white_level),
        source=path,
    )


def demosaic_bilinear_ea(mosaic: Mosaic) -> np.ndarray:
    """Black-subtract, normalise to white = 1, and demosaic with OpenCV's edge-aware method."""
    black = _tile(mosaic.black_level, mosaic.data.shape)  # [H, W]
    norm = np.clip((mosaic.data - black) / (mosaic.white_level - black), 0.0, 1.0)
    as16 = np.round(norm * 65535.0).astype(np.uint16)
    pattern_name = next(k for k, v in _PATTERN_INDEX.items() if np.array_equal(v, mosaic.pattern))
    return cv2.cvtColor(as16, _CV_CODE[pattern_name]).astype(np.float32) / 65535.0  # [H, W, 3]


def develop_mosaic(
    mosaic: Mosaic, settings: DevelopSettings, wb: WhiteBalance, matrix: np.ndarray | None = None
) -> Developed:
    """The headerless path: same flags and tail as `develop_raw`, demosaiced by OpenCV."""
    data = mosaic.data.astype(np.float32)
    clipped, p99 = _signal_stats(data, mosaic.black_level, mosaic.white_level, settings)
    camera_rgb = demosaic_bilinear_ea(mosaic) * np.asarray(wb.gains, dtype=np.float32)  # [H, W, 3]
    matrix_source: MatrixSource = "file" if matrix is not None else "none"
    matrix = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    return _finish(camera_rgb, mosaic.source, matrix, matrix_source, wb, clipped, p99, settings)


def estimate_black_level(mosaic: np.ndarray, percentile: float = 0.1) -> tuple[float, ...]:
    """Black level when nobody states it: a low percentile of each photosite of the 2x2 tile.

    Zero-valued photosites are left out (dead corners past the lens's image circle read 0 on
    the infiniteisp capture, although the sensor pedestal is far above 0). This assumes some
    near-black content in frame (a chart's black patch, its frame), and overestimates the
    black level by that content's small signal; `colour.black_level_from_neutrals` refines it.
    """
    levels = []
    for y in range(2):
        for x in range(2):
            site = mosaic[y::2, x::2]
            site = site[site > 0]
            levels.append(float(np.percentile(site, percentile)) if site.size else 0.0)
    return tuple(levels)
