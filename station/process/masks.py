"""Stone masks from a clean plate, without downloaded weights.

Three steps (pipeline.md measured why each is needed):
1. Plate difference that ignores the contact shadow and exposure drift: the plate is scaled
   to the shot by a robust per-channel gain on the frame border (never the stone), then a
   pixel is stone if it is brighter than the plate, darker than any contact shadow can make
   it, or its chromaticity moves (shadows only darken and keep chroma). Thresholds follow
   the photon noise measured on the border. The sparse cues are closed into one blob and
   its convex hull (stones are nearly convex) is the first guess.
2. GrabCut, seeded from that guess as a trimap, on a crop around the object: it fills in
   what the sparse cues of a pale stone miss and puts the boundary on the image edge.
3. Cleaning: largest connected component, holes filled.
Known limit: where a pale stone's shaded side is darker than the plate behind it with the
plate's chroma, nothing in the pixels tells it from a contact shadow, and it is lost
(low elevations, where the stone stands against the backdrop; see tests/test_masks.py).
`check_masks` then flags masks that are empty, fill the frame, touch the frame border, or
jump in area against their neighbours on the same turntable ring.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from station.errors import BadInputError


@dataclass(frozen=True)
class MaskSettings:
    border_fraction: float = 0.06  # width of the frame strip used for gain and noise (fraction of the short side)
    noise_sigmas: float = 4.0  # a cue fires this many border-noise sigmas away from the plate
    min_ratio_dev: float = 0.04  # never fire on luminance changes smaller than this (exposure flicker)
    shadow_floor: float = 0.12  # ratios below this are too dark to be a contact shadow
    min_chroma_dev: float = 0.02  # chromaticity distance that always counts as stone
    grabcut_median_px: int = 3
    grabcut_seed: int = 0
    grabcut_iters: int = 4
    grabcut_margin: float = 0.15  # crop margin around the seed, fraction of its size
    probable_band_px: int = 10  # width of the uncertain band GrabCut may move the boundary in
    seed_closing_px: int = 9  # bridges the gaps a weakly contrasting stone leaves in the sure cues
    seed_blob_fraction: float = 0.05  # smaller blobs than this share of the biggest are noise
    convex_seed: bool = True  # stones are nearly convex: the hull of the cues is a good first guess


@dataclass(frozen=True)
class MaskCheckSettings:
    min_area_fraction: float = 0.002
    max_area_fraction: float = 0.85
    max_area_jump: float = 1.6  # area ratio to the nearer neighbour beyond which a view is suspect


@dataclass
class MaskCheck:
    """Verdict on one mask; `reasons` is empty when the mask looks plausible."""

    name: str
    area_fraction: float
    reasons: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.reasons


def _luma(image: np.ndarray) -> np.ndarray:
    return image @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # [H, W]


def _border(shape: tuple[int, int], fraction: float) -> np.ndarray:
    h, w = shape
    k = max(2, int(round(min(h, w) * fraction)))
    strip = np.zeros((h, w), dtype=bool)
    strip[:k], strip[-k:], strip[:, :k], strip[:, -k:] = True, True, True, True
    return strip


def difference_mask(shot: np.ndarray, plate: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """Sure-stone pixels [H, W] bool from shadow-aware plate differencing (sparse on weak stones)."""
    if shot.shape != plate.shape or shot.ndim != 3:
        raise BadInputError(f"shot {shot.shape} and plate {plate.shape} must be matching [H, W, 3] images")
    eps = 1e-4
    border = _border(shot.shape[:2], settings.border_fraction)
    plate = _plate_matched(shot, plate, settings)
    smooth_s = cv2.GaussianBlur(shot, (0, 0), 1.0)
    smooth_p = cv2.GaussianBlur(plate, (0, 0), 1.0)
    ls, lp = _luma(smooth_s) + eps, _luma(smooth_p) + eps
    log_ratio = np.log(ls / lp)  # [H, W]
    chroma = np.linalg.norm(smooth_s / ls[..., None] - smooth_p / lp[..., None], axis=2)  # [H, W]

    # photon noise: a cue's spread scales as 1/sqrt(signal); calibrate that on the border strip
    signal = np.sqrt(np.maximum(lp / float(np.median(lp[border])), 1e-3))  # [H, W]

    def zscore(values: np.ndarray) -> np.ndarray:
        scaled = values * signal
        v = scaled[border]
        spread = float(1.4826 * np.median(np.abs(v - np.median(v)))) + 1e-6
        return (scaled - float(np.median(v))) / spread

    n = settings.noise_sigmas
    brighter = (zscore(log_ratio) > n) & (log_ratio > settings.min_ratio_dev)
    too_dark = log_ratio < np.log(settings.shadow_floor)
    chroma_cue = (zscore(chroma) > n) & (chroma > settings.min_chroma_dev)
    opening = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    sure = cv2.morphologyEx((brighter | too_dark | chroma_cue).astype(np.uint8), cv2.MORPH_OPEN, opening)
    return sure.astype(bool)


def _plate_matched(shot: np.ndarray, plate: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """The plate scaled to the shot's exposure by a robust per-channel gain on the frame border."""
    border = _border(shot.shape[:2], settings.border_fraction)
    gain = np.median(shot[border] / np.maximum(plate[border], 1e-4), axis=0)  # [3]
    return plate * gain.astype(np.float32)


def largest_component_filled(mask: np.ndarray) -> np.ndarray:
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return np.zeros_like(mask, dtype=bool)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return ndimage.binary_fill_holes(labels == biggest)


def _grabcut_input(shot: np.ndarray, median_px: int) -> np.ndarray:
    """8-bit BGR for GrabCut, contrast-stretched so dark and pale stones keep their detail.

    A small median filter melts speckle grains into the stone's body colour, so GrabCut's
    colour model of a speckled stone is one cluster instead of grains that look like plate.
    """
    lo, hi = np.percentile(shot, [0.5, 99.5])
    encoded = np.clip((shot - lo) / max(hi - lo, 1e-6), 0.0, 1.0) ** (1 / 2.2)
    image = np.ascontiguousarray((encoded[:, :, ::-1] * 255).astype(np.uint8))
    return cv2.medianBlur(image, median_px) if median_px > 1 else image


def seed_from_cues(sure: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """One solid first guess from sparse cues: close the gaps, gather the blobs, take their hull.

    A pale stone lights up only in patches (where its shading departs from the backdrop), so
    blobs near the biggest one and not much smaller than it count too; far or tiny blobs
    (sensor noise, chart edges) do not.
    """
    closing = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (settings.seed_closing_px,) * 2)
    closed = cv2.morphologyEx(sure.astype(np.uint8), cv2.MORPH_CLOSE, closing)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
    if count <= 1:
        return np.zeros(sure.shape, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    main = 1 + int(np.argmax(areas))
    x, y, w, h = stats[main, :4]
    reach = max(w, h)
    seed = np.zeros(sure.shape, dtype=bool)
    for i in range(1, count):
        bx, by, bw, bh, area = stats[i]
        gap_x = max(0, max(bx, x) - min(bx + bw, x + w))
        gap_y = max(0, max(by, y) - min(by + bh, y + h))
        if i == main or (area >= settings.seed_blob_fraction * areas.max() and max(gap_x, gap_y) <= reach):
            seed |= labels == i
    if settings.convex_seed:
        hull = cv2.convexHull(cv2.findNonZero(seed.astype(np.uint8)))
        seed = cv2.fillConvexPoly(np.zeros(seed.shape, np.uint8), hull, 1).astype(bool)
    return seed


def refine_grabcut(shot: np.ndarray, sure: np.ndarray, seed: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """GrabCut on a crop around the seed: sure-stone stays stone, far background stays background."""
    if not seed.any():
        return seed
    ys, xs = np.nonzero(seed)
    h, w = seed.shape
    band_px = settings.probable_band_px
    my = int((ys.max() - ys.min() + 1) * settings.grabcut_margin) + band_px + 2
    mx = int((xs.max() - xs.min() + 1) * settings.grabcut_margin) + band_px + 2
    y0, y1 = max(0, ys.min() - my), min(h, ys.max() + my + 1)
    x0, x1 = max(0, xs.min() - mx), min(w, xs.max() + mx + 1)
    band = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1,) * 2)
    crop_seed = seed[y0:y1, x0:x1].astype(np.uint8)
    core = cv2.erode(crop_seed, band).astype(bool) & sure[y0:y1, x0:x1]
    grown = cv2.dilate(crop_seed, band).astype(bool)
    trimap = np.full(crop_seed.shape, cv2.GC_BGD, dtype=np.uint8)
    trimap[grown] = cv2.GC_PR_BGD
    trimap[crop_seed.astype(bool)] = cv2.GC_PR_FGD
    trimap[core] = cv2.GC_FGD
    if not (trimap == cv2.GC_BGD).any() or not np.isin(trimap, (cv2.GC_FGD, cv2.GC_PR_FGD)).any():
        return seed
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    image = _grabcut_input(shot[y0:y1, x0:x1], settings.grabcut_median_px)
    cv2.setRNGSeed(settings.grabcut_seed)  # GrabCut's k-means draws from OpenCV's global RNG
    cv2.grabCut(image, trimap, None, bgd, fgd, settings.grabcut_iters, cv2.GC_INIT_WITH_MASK)
    out = np.zeros_like(seed)
    out[y0:y1, x0:x1] = np.isin(trimap, (cv2.GC_FGD, cv2.GC_PR_FGD))
    return out


def compute_mask(
    shot_linear: np.ndarray, plate_linear: np.ndarray, settings: MaskSettings = MaskSettings()
) -> np.ndarray:
    """Stone mask [H, W] bool for a developed shot and the clean plate of the same elevation."""
    shot, plate = shot_linear.astype(np.float32), plate_linear.astype(np.float32)
    sure = difference_mask(shot, plate, settings)
    seed = seed_from_cues(sure, settings)
    return largest_component_filled(refine_grabcut(shot, sure, seed, settings))


def check_masks(
    masks: list[np.ndarray], names: list[str], settings: MaskCheckSettings = MaskCheckSettings()
) -> list[MaskCheck]:
    """Flag implausible masks. `masks` is one turntable ring in azimuth order (it wraps around)."""
    if len(masks) != len(names):
        raise BadInputError(f"{len(masks)} masks but {len(names)} names")
    areas = np.array([float(m.mean()) for m in masks])
    checks = []
    for i, (mask, name) in enumerate(zip(masks, names)):
        check = MaskCheck(name=name, area_fraction=float(areas[i]))
        if areas[i] < settings.min_area_fraction:
            check.reasons.append(f"empty: covers {areas[i]:.2%} of the frame")
        elif areas[i] > settings.max_area_fraction:
            check.reasons.append(f"fills the frame: covers {areas[i]:.2%}")
        if mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any():
            check.reasons.append("touches the frame border (stone cut off or background leaked in)")
        if len(masks) >= 3:
            # outside the range its two neighbours span, widened by the allowed jump: one odd view is
            # flagged, and its normal neighbours are not dragged along
            pair = (areas[i - 1], areas[(i + 1) % len(masks)])
            if areas[i] > max(pair) * settings.max_area_jump or areas[i] * settings.max_area_jump < min(pair):
                check.reasons.append(
                    f"area {areas[i]:.2%} jumps against its neighbouring views ({pair[0]:.2%}, {pair[1]:.2%})"
                )
        checks.append(check)
    return checks
