"""White balance from the backdrop plate, and colour correction against a ColorChecker.

The chart locator is ours, deliberately simple: colour-checker-detection's offline detector
would pull in a second OpenCV build (opencv-python beside our headless one) and OpenImageIO
(rig.md), so it is not used. A ColorChecker Classic in a light booth is a large dark card
with 24 bright-ish holes; we take the largest dark blob not touching the frame, its holes
as patch candidates, fit the 6x4 grid to their centres, and try the chart's possible
orientations, keeping the one a 3x3 correction fits best. Without a chart, the camera
matrix from the raw stays in charge (develop.py).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from types import ModuleType

import cv2
import numpy as np
from scipy import ndimage

from station.errors import BadInputError
from station.process.develop import WhiteBalance

CHART_NAME = "ColorChecker24 - After November 2014"
NEUTRAL_PATCHES = slice(18, 24)  # white 9.5 ... black 2 on the bottom row


@functools.cache
def _colour() -> ModuleType:
    """colour-science, imported on first use: it is one of the slowest imports every stage process start
    pays (the batch forkserver preloads this module), and only a scan with a chart in it needs it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # colour warns at import that matplotlib is absent
        import colour
    return colour


class ChartNotFoundError(BadInputError):
    """No ColorChecker could be located; the caller falls back to the camera matrix."""


@dataclass(frozen=True)
class ChartFit:
    """Where the chart is, what it measured, and how well a 3x3 correction brings it home."""

    centres: np.ndarray  # [24, 2] x, y pixel centres in the analysed image, chart reading order
    measured: np.ndarray  # [24, 3] linear RGB as measured (before correction)
    matrix: np.ndarray  # [3, 3] measured -> linear sRGB (Cheung 2004, 3 terms)
    delta_e_before: float  # mean CIE 2000 after exposure and white balance on the neutrals only
    delta_e_after: float  # mean CIE 2000 after the 3x3 correction


def reference_srgb_linear() -> np.ndarray:
    """The published chart values (D50 xyY), Bradford-adapted to D65, as linear sRGB [24, 3]."""
    colour = _colour()
    chart = colour.CCS_COLOURCHECKERS[CHART_NAME]
    xyz = colour.xyY_to_XYZ(np.array(list(chart.data.values())))
    return colour.XYZ_to_RGB(
        xyz, colour.RGB_COLOURSPACES["sRGB"], illuminant=chart.illuminant, chromatic_adaptation_transform="Bradford"
    )


def srgb_linear_to_lab(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB -> CIE Lab under D65, the space the ΔE00 figures are computed in."""
    colour = _colour()
    xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], illuminant=None)
    return colour.XYZ_to_Lab(xyz, colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])


def mean_delta_e00(rgb: np.ndarray, reference: np.ndarray) -> float:
    return float(np.mean(_colour().delta_E(srgb_linear_to_lab(rgb), srgb_linear_to_lab(reference), method="CIE 2000")))


def white_balance_from_linear(camera_rgb: np.ndarray, source: str, clip: float = 0.98) -> WhiteBalance:
    """Gains that make the neutral backdrop grey: ratio of channel sums over its brighter half.

    The plate shows only backdrop and turntable, both neutral; the darker half (vignetted
    corners, shadowed rig parts) is noisier and may hold coloured hardware, and clipped
    photosites carry no colour, so both are left out.
    """
    pixels = camera_rgb.reshape(-1, 3)  # [N, 3]
    valid = np.all(pixels < clip, axis=1) & np.all(pixels > 0, axis=1)
    if valid.sum() < 100:
        raise BadInputError(f"{source}: too few unclipped, non-black pixels to take a white balance from")
    luma = pixels[valid].mean(axis=1)
    bright = pixels[valid][luma >= np.median(luma)]
    sums = bright.sum(axis=0)
    return WhiteBalance((float(sums[1] / sums[0]), 1.0, float(sums[1] / sums[2])), source=source)


def _chart_blob(luma: np.ndarray) -> np.ndarray:
    """The chart card: the largest dark component that does not touch the frame, holes filled."""
    dark = luma < 0.25 * np.percentile(luma, 90)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(dark.astype(np.uint8), connectivity=8)
    h, w = luma.shape
    best, best_area = 0, 0
    for i in range(1, count):
        x, y, bw, bh, area = stats[i]
        touches = x == 0 or y == 0 or x + bw >= w or y + bh >= h
        if not touches and area > best_area:
            best, best_area = i, area
    if best == 0:
        raise ChartNotFoundError("no dark chart card found away from the frame border")
    return labels == best


def _patch_centres(luma: np.ndarray) -> tuple[np.ndarray, float]:
    """Centres [K, 2] of square holes of one common size inside the chart card, and their pitch."""
    card = _chart_blob(luma)
    holes = ndimage.binary_fill_holes(card) & ~card
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=4)
    if count < 2:
        raise ChartNotFoundError("the dark card has no patch-like holes")
    areas = stats[1:, 4].astype(np.float64)
    squareness = stats[1:, 4] / np.maximum(stats[1:, 2] * stats[1:, 3], 1)
    typical = np.median(areas[areas > 0.2 * areas.max()])
    keep = (areas > 0.5 * typical) & (areas < 1.6 * typical) & (squareness > 0.7)
    centres = centroids[1:][keep]
    if len(centres) < 12:
        raise ChartNotFoundError(f"only {len(centres)} patch-like holes found (need at least 12 of 24)")
    dists = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.eye(len(centres)) * 1e9
    return centres, float(np.median(dists.min(axis=1)))


def _grid_fits(centres: np.ndarray, pitch: float) -> list[np.ndarray]:
    """Candidate [24, 2] centre sets in chart reading order, one per plausible orientation."""
    origin = centres.min(axis=0)
    cells = np.round((centres - origin) / pitch).astype(int)  # [K, 2] column, row
    cols, rows = cells.max(axis=0) + 1
    if {cols, rows} != {6, 4}:
        raise ChartNotFoundError(f"patches form a {cols}x{rows} grid, not 6x4")
    design = np.column_stack([cells, np.ones(len(cells))])  # affine: centre = [c, r, 1] @ A
    affine, *_ = np.linalg.lstsq(design, centres, rcond=None)  # [3, 2]
    cc, rr = np.meshgrid(np.arange(cols), np.arange(rows))  # [rows, cols]
    grid = np.column_stack([cc.ravel(), rr.ravel(), np.ones(cc.size)]) @ affine  # [24, 2] row-major
    layout = grid.reshape(rows, cols, 2)
    if cols != 6:
        layout = np.transpose(layout, (1, 0, 2))[:, ::-1]  # portrait: turn to landscape reading order
    # upright and upside down, plus both mirror images (a chart seen via a mirror, or rendered flipped)
    return [layout.reshape(24, 2), layout[::-1, ::-1].reshape(24, 2),
            layout[::-1].reshape(24, 2), layout[:, ::-1].reshape(24, 2)]


def _sample(image: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    """Median colour in a square window around each centre: robust to dust and edge bleed."""
    out = []
    for x, y in np.round(centres).astype(int):
        window = image[max(0, y - half) : y + half + 1, max(0, x - half) : x + half + 1].reshape(-1, 3)
        out.append(np.median(window, axis=0))
    return np.array(out)  # [24, 3]


def fit_chart(measured: np.ndarray) -> tuple[np.ndarray, float, float]:
    """3x3 correction measured -> reference, with mean ΔE00 before (neutral-only balance) and after."""
    reference = reference_srgb_linear()  # [24, 3]
    neutral = measured[NEUTRAL_PATCHES]
    gains = reference[NEUTRAL_PATCHES].sum(axis=0) / np.maximum(neutral.sum(axis=0), 1e-9)
    before = mean_delta_e00(measured * gains, reference)
    matrix = _colour().matrix_colour_correction(measured, reference, method="Cheung 2004")
    after = mean_delta_e00(measured @ matrix.T, reference)
    return matrix, before, after


def locate_and_fit_chart(linear_rgb: np.ndarray) -> ChartFit:
    """Find a ColorChecker Classic filling much of the frame and fit a colour correction to it."""
    luma = linear_rgb.mean(axis=2)  # [H, W]
    centres, pitch = _patch_centres(luma)
    best: ChartFit | None = None
    for candidate in _grid_fits(centres, pitch):
        measured = _sample(linear_rgb, candidate, half=max(1, int(pitch * 0.18)))
        matrix, before, after = fit_chart(measured)
        if best is None or after < best.delta_e_after:
            best = ChartFit(candidate, measured, matrix, before, after)
    assert best is not None  # _grid_fits always yields candidates
    return best


def black_level_from_neutrals(measured: np.ndarray) -> np.ndarray:
    """Per-channel offset [3] of the chart's six neutrals against their published luminance.

    The neutrals' signal is proportional to their reflectance, so a straight-line fit of
    signal against reference Y crosses zero reflectance at the sensor's black level (plus
    any veiling flare, which should be subtracted too). `measured` must not be black-subtracted.
    """
    ref_y = reference_srgb_linear()[NEUTRAL_PATCHES].mean(axis=1)  # [6]
    design = np.column_stack([ref_y, np.ones_like(ref_y)])
    coeffs, *_ = np.linalg.lstsq(design, measured[NEUTRAL_PATCHES], rcond=None)  # [2, 3]
    return coeffs[1]
