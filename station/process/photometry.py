"""Vignetting and exposure, measured from the scan's own frames so every view trains with the same colours.

- Flat field: the empty-plate frames show only smooth, evenly lit surfaces (backdrop, turntable plate)
  split by sharp edges. Each region between edges gets its own plane of light; what all regions of all
  plates share, a falloff centred on the lens, log V = a rho^2 + b rho^4, is the vignetting.
- Exposure within a ring: the camera does not move during a ring, so the backdrop on the frame border is
  the same light in every shot and in the ring's plate; the median ratio there is the exposure error.
- Exposure across rings: a stone point posing triangulated, seen from two rings at the same turn of the
  plate, stood the same way in the lab's light both times, so it looks the same (matte stone) but for the
  rings' exposures: the median log ratio over such points gives each ring's gain.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from station.errors import BadInputError

_FLOOR = 1e-4  # linear value below which a log stops meaning anything


@dataclass(frozen=True)
class FlatField:
    """The lens's radial falloff, log V(rho) = a rho^2 + b rho^4, rho = radius over the half-diagonal."""

    a: float = 0.0
    b: float = 0.0

    def at(self, height: int, width: int) -> np.ndarray:
        """[H, W] float32 share of the light reaching each pixel (1 on the axis)."""
        ys = np.arange(height) + 0.5 - height / 2.0
        xs = np.arange(width) + 0.5 - width / 2.0
        rho2 = (ys[:, None] ** 2 + xs[None, :] ** 2) / ((height / 2.0) ** 2 + (width / 2.0) ** 2)
        return np.exp(self.a * rho2 + self.b * rho2 * rho2).astype(np.float32)

    @property
    def corner_stops(self) -> float:
        """Light lost at the corners, in stops (what an operator compares with the lens's data sheet)."""
        return float(-(self.a + self.b) / np.log(2.0))

    def correct(self, image: np.ndarray) -> np.ndarray:
        """`image` [H, W, 3] linear as if the lens did not vignette."""
        return image / self.at(*image.shape[:2])[..., None]


@dataclass(frozen=True)
class FlatFieldSettings:
    fit_width: int = 160  # plates are averaged down to this width to fit (the falloff is smooth)
    edge_log_step: float = 0.03  # a log-luminance step per fit pixel above this separates two surfaces
    min_region_fraction: float = 0.02  # surfaces smaller than this share of the frame are left out
    trim_mad: float = 4.0  # pixels further than this many MADs from the first fit are dropped for the second


def _luminance(image: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(image.mean(axis=2), _FLOOR))


def _plate_rows(log_lum: np.ndarray, settings: FlatFieldSettings) -> tuple[np.ndarray, list[np.ndarray]]:
    """The pixels of one plate's smooth regions: their log luminance [N] and per region the design columns
    (rho^2, rho^4, then 1, x, y for the region's own plane) as a list of [N_r, 5] blocks."""
    h, w = log_lum.shape
    smooth = cv2.GaussianBlur(log_lum.astype(np.float32), (0, 0), 0.7)
    gy, gx = np.gradient(smooth)
    edges = ndimage.binary_dilation(np.hypot(gx, gy) > settings.edge_log_step, iterations=1)
    labels, count = ndimage.label(~edges)
    ys, xs = np.mgrid[0:h, 0:w]
    ys, xs = (ys + 0.5 - h / 2.0) / (h / 2.0), (xs + 0.5 - w / 2.0) / (w / 2.0)
    rho2 = (ys**2 * h * h + xs**2 * w * w) / (h * h + w * w)
    values, blocks = [], []
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    for region in np.flatnonzero(sizes >= settings.min_region_fraction * h * w):
        if region == 0:
            continue
        inside = labels == region
        values.append(log_lum[inside])
        blocks.append(np.column_stack([rho2[inside], rho2[inside] ** 2, np.ones(inside.sum()), xs[inside], ys[inside]]))
    return np.concatenate(values) if values else np.zeros(0), blocks


def fit_flat_field(plates: list[np.ndarray], settings: FlatFieldSettings = FlatFieldSettings()) -> FlatField:
    """The vignetting shared by the plates [H, W, 3] (linear), fitted as the module docstring says."""
    values, blocks = [], []
    for plate in plates:
        small = cv2.resize(plate, (settings.fit_width, max(2, round(plate.shape[0] * settings.fit_width
                                                                    / plate.shape[1]))), interpolation=cv2.INTER_AREA)
        v, b = _plate_rows(_luminance(small), settings)
        values.append(v)
        blocks += b
    if not blocks:
        raise BadInputError("flat field: the plates show no smooth surface to measure the lens's falloff on")
    y = np.concatenate(values)
    rows = sum(len(b) for b in blocks)
    design = np.zeros((rows, 2 + 3 * len(blocks)))
    start = 0
    for i, block in enumerate(blocks):
        design[start:start + len(block), :2] = block[:, :2]
        design[start:start + len(block), 2 + 3 * i:5 + 3 * i] = block[:, 2:]
        start += len(block)
    coef = np.linalg.lstsq(design, y, rcond=None)[0]
    residual = y - design @ coef
    mad = float(np.median(np.abs(residual - np.median(residual)))) + 1e-9
    keep = np.abs(residual) <= settings.trim_mad * 1.4826 * mad
    coef = np.linalg.lstsq(design[keep], y[keep], rcond=None)[0]
    return FlatField(float(coef[0]), float(coef[1]))


def border(shape: tuple[int, int], fraction: float) -> np.ndarray:
    """[H, W] bool: the frame's outer strip, `fraction` of the short side wide (never the stone)."""
    k = max(1, round(fraction * min(shape)))
    strip = np.zeros(shape, dtype=bool)
    strip[:k], strip[-k:], strip[:, :k], strip[:, -k:] = True, True, True, True
    return strip


def exposure_to_plate(shot: np.ndarray, plate: np.ndarray, fraction: float = 0.06) -> float:
    """The gain that brings `shot` [H, W, 3] to its ring's `plate` exposure: median luminance ratio on the border."""
    if shot.shape != plate.shape:
        raise BadInputError(f"exposure: shot {shot.shape} and plate {plate.shape} differ in size")
    strip = border(shot.shape[:2], fraction)
    ratio = np.maximum(plate[strip].mean(axis=1), _FLOOR) / np.maximum(shot[strip].mean(axis=1), _FLOOR)
    return float(np.median(ratio))


def ring_gains(observations: list[tuple[int, str, float, float]], min_pairs: int = 20) -> dict[str, float]:
    """Per ring, the gain that brings it to the scan's common exposure, from (point id, ring, azimuth, log
    luminance) observations of triangulated points. Only a point seen from two rings at the same turn of the
    plate is compared: the stone then stood the same way in the lab's light, so only the exposure differs.
    Rings linked to the rest by fewer than `min_pairs` such points keep 1."""
    rings = sorted({ring for _, ring, _, _ in observations})
    seen: dict[tuple[int, float], dict[str, float]] = {}
    for point, ring, azimuth, value in observations:
        seen.setdefault((point, round(azimuth % 360.0, 2)), {})[ring] = value
    differences: dict[tuple[int, int], list[float]] = {}
    for by_ring in seen.values():
        names = sorted(by_ring)
        for i, first in enumerate(names):
            for second in names[i + 1:]:
                differences.setdefault((rings.index(first), rings.index(second)), []).append(
                    by_ring[first] - by_ring[second])
    pairs = [(i, j, float(np.median(d)), len(d)) for (i, j), d in differences.items() if len(d) >= min_pairs]
    linked = sorted({i for i, j, _, _ in pairs} | {j for i, j, _, _ in pairs})
    if len(linked) < 2:
        return {r: 1.0 for r in rings}
    # log exposure per linked ring: each pair's median difference, weighted by its count; the mean fixed at 0
    design = np.zeros((len(pairs) + 1, len(linked)))
    target = np.zeros(len(pairs) + 1)
    for row, (i, j, difference, count) in enumerate(pairs):
        weight = np.sqrt(count)
        design[row, linked.index(i)], design[row, linked.index(j)], target[row] = weight, -weight, weight * difference
    design[-1] = 1.0
    exposure = np.linalg.lstsq(design, target, rcond=None)[0]
    gains = {r: 1.0 for r in rings}
    gains.update({rings[i]: float(np.exp(-exposure[k])) for k, i in enumerate(linked)})
    return gains
