"""Masks for imported photos that come without any, shot against a dark backdrop (Middlebury's black cloth).

There is no clean plate, so the backdrop is modelled only as "dark, and reaching the frame border":
1. Luminance, median-filtered (3x3) against sensor noise without blurring the outline. Otsu's
   threshold per image (never below a floor, so a nearly black frame does not split its noise)
   separates the lit object from the backdrop.
2. Hysteresis for shadowed faces: pixels between a fraction of that threshold and the threshold are
   object unless their dark region reaches the frame border. Lit cloth at the frame's sides is that
   dim too, but it runs off the frame; a shadowed column or pediment is enclosed by the object.
3. Cleaning: a small closing bridges dark grooves cut into the object's outline, a small opening
   drops one-pixel spurs, components under a fraction of the largest go (specks), and only holes
   small against the object are filled: a large hole is backdrop seen between columns.
Known limit: a dim backdrop feature that touches the object but not the frame border (a lit fold of
the cloth) stays attached as a small spur.
The mask is hard (0 or 255), with no feather: a threshold says nothing about how much of an edge
pixel the object covers, and the importer treats any value between as coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu


@dataclass(frozen=True)
class DarkBackdropSettings:
    floor: float = 12.0  # 8-bit luminance no object pixel is darker than, whatever Otsu says
    shadow_fraction: float = 0.5  # shadowed object pixels reach down to this fraction of the threshold
    close_px: int = 7
    min_component: float = 0.1  # of the largest component's area
    max_hole: float = 0.01  # of the object's area: larger holes are backdrop seen through the object


def _disk(size: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


def _reaching_border(region: np.ndarray) -> np.ndarray:
    """The parts of `region` connected (8-neighbour) to the frame border."""
    _, labels = cv2.connectedComponents(region.astype(np.uint8), connectivity=8)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return np.isin(labels, edge[edge > 0])


def _fill_small_holes(mask: np.ndarray, max_area: float) -> np.ndarray:
    """`mask` with every enclosed hole of at most `max_area` pixels filled; larger holes stay open."""
    holes = ndimage.binary_fill_holes(mask) & ~mask
    _, labels, stats, _ = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=4)
    small = 1 + np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] <= max_area)
    return mask | np.isin(labels, small)


def dark_backdrop_mask(rgb: np.ndarray, settings: DarkBackdropSettings = DarkBackdropSettings()) -> np.ndarray:
    """uint8 [H, W] mask (255 object) of an 8-bit RGB image [H, W, 3] of a lit object on a dark backdrop."""
    luma = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    luma = cv2.medianBlur(luma, 3)
    high = max(float(threshold_otsu(luma)) if np.ptp(luma) > 0 else settings.floor, settings.floor)
    low = max(settings.shadow_fraction * high, settings.floor)
    lit = luma > high
    dim = (luma > low) & ~lit
    mask = (lit | (dim & ~_reaching_border(dim))).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(settings.close_px))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(3))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count <= 1:
        return np.zeros(luma.shape, np.uint8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    mask = np.isin(labels, 1 + np.flatnonzero(areas >= settings.min_component * areas.max()))
    mask = _fill_small_holes(mask, settings.max_hole * mask.sum())
    return mask.astype(np.uint8) * 255
