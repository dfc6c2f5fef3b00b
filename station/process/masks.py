"""Stone masks from a clean plate, without downloaded weights.

The plate tells what the background should look like at every pixel, so the mask is a binary
labelling with a per-pixel background model rather than a guess from colours alone:
1. Seed: plate differencing that ignores contact shadow and exposure drift. The plate is
   scaled to the shot by a robust per-channel gain on the frame border (never the stone); a
   pixel is sure stone if it is brighter than the plate, darker than any contact shadow can
   make it, or its chromaticity moves (shadows only darken and keep chroma), with thresholds
   from the photon noise measured on the border. The convex hull of those sparse cues
   (stones are nearly convex) is the first guess.
2. Graph cut (min-cut over 8-neighbour pixels, Boykov-Kolmogorov max-flow, maxflow.py), iterated with its models:
   - background: the plate times a smooth contact-shadow field, fitted as a local plane to
     the current background in log space so it extrapolates up to the stone's edge. Its scale
     follows the stone's size in pixels, as the contact shadow's does (a low camera squeezes the
     shadow into a few rows, which a wider plane lags). A field fitted around the stone, unlike a
     global "darker and grey" shadow class, leaves a textured stone's shaded rim alone. Only when
     the stone's own colour sets it apart from the plate does the fit also take plate-coloured,
     shadowed pixels next to it, the steep wedge under a rounded base that the plane misses;
   - stone: a smoothed colour histogram (log RGB) of the current stone pixels;
   - a small bonus inside the seed hull (nearly convex stones);
   - a contrast-sensitive smoothness term on the noise-normalised difference between the shot
     and the shadowed plate, so the boundary follows edges of the stone, not of the plate, the
     chart or the contact shadow's own steep gradient (which would otherwise pull it down).
3. Matting of the boundary: each edge pixel is unmixed against the shadowed plate and the stone
   colour beside it, and is stone if the stone covers at least half of it.
4. Cleaning: largest connected component, holes filled.
5. The matte (`compute_matte`): the coverage of the edge pixels and the stone's own colour there,
   which is what training should match (see `Matte`), estimated with the colour of the solid stone
   nearby as a prior (`unmix`), so a barely covered pixel never takes a colour neither has.
Known limit of one view: a pale stone's shaded side that is smooth, grey and darker than the plate
is explained by the shadow field as well as by the stone, and is lost. On the simulated stones it
fades into its own contact shadow with no edge at all (low elevations); where an edge does
separate them, the smoothness term alone cannot outweigh the field (tests/test_masks.py). Other
views do see it: once the scan is posed, cross_view.py passes the silhouette the other rings
predict (`silhouette`), which joins the seed and weighs in the cut as a prior for stone.
`check_masks` then flags masks that are empty, fill the frame, touch the frame border, or
jump in area against their neighbours on the same turntable ring.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import cv2
import numpy as np
from numba import njit
from scipy import ndimage

from station.errors import BadInputError
from station.process import maxflow

_LOG_FLOOR = 1e-4  # linear value below which log ratios stop meaning anything
_NATS_TO_CAPACITY = 100  # max-flow needs integer capacities: hundredths of a nat
_MAX_NATS = 50.0  # no single pixel's evidence counts for more (keeps capacities in int32)


@dataclass(frozen=True)
class MaskSettings:
    border_fraction: float = 0.06  # width of the frame strip used for gain and noise (fraction of the short side)
    noise_sigmas: float = 4.0  # a seed cue fires this many border-noise sigmas away from the plate
    min_ratio_dev: float = 0.04  # never fire on luminance changes smaller than this (exposure flicker)
    shadow_floor: float = 0.12  # ratios below this are too dark to be a contact shadow
    min_chroma_dev: float = 0.02  # chromaticity distance that always counts as stone
    seed_closing_px: int = 9  # bridges the gaps a weakly contrasting stone leaves in the sure cues
    seed_blob_fraction: float = 0.05  # smaller blobs than this share of the biggest are noise
    crop_margin: float = 0.35  # the cut runs on the seed's box grown by this fraction of its size
    cut_iterations: int = 3  # cut, refit shadow field and stone colours, cut again
    # A round that moves no more than this share of the stone's pixels has settled: the next would move only a few
    # edge pixels, so the cut ends there.
    settled_fraction: float = 1e-3
    shadow_field_fraction: float = 0.022  # Gaussian scale of the shadow's local plane, per sqrt(seed area) px
    min_shadow_field_px: float = 1.5  # below this the plane follows the noise more than the shadow
    shadow_field_gap_px: int = 2  # background this close to the stone is left out of the fit (mixed pixels)
    shadow_slack: float = 0.03  # log-ratio error allowed to the fitted field, on top of sensor noise
    plate_chroma_chi2: float = 4.0  # colour this close to the plate's (chi-square, 2 dof) could be shadow
    max_plate_coloured_stone: float = 0.1  # a stone with fewer plate-coloured pixels than this is told by colour
    matte_boundary: bool = True  # relabel the boundary pixels by their coverage (see matte_boundary)
    max_alpha_sigma: float = 0.15  # boundary pixels whose coverage is less certain keep the cut's label
    edge_colour_px: float = 1.5  # Gaussian scale of the solid stone whose colour an edge pixel's colour leans on
    edge_colour_floor: float = 0.02  # relative spread the stone's colour keeps beyond what its pixels show
    colour_bins: int = 24  # per log-RGB axis of the stone colour histogram
    colour_floor: float = 1e-3  # density any colour keeps under the stone model (unseen grains, highlights)
    hull_prior_nats: float = 3.0  # bonus for stone inside the seed hull
    # The stone's silhouette as the other rings predict it (cross_view.py) is worth these nats of stone, short of
    # a band on its edge where the prediction is itself a pixel out; on its part that may be a roof over the stone
    # (cross_view.roofed_part) only `roof_prior_nats`, as backdrop as pale as a pale stone may lie under it.
    silhouette_prior_nats: float = 4.0
    roof_prior_nats: float = 1.0
    silhouette_band_px: int = 1
    smoothness: float = 9.0  # nats per unit boundary length across a flat (edgeless) region
    contrast_blur_px: float = 1.0  # the smoothness term reads edges on a lightly denoised difference
    # Larger frames are masked at this longest side and the mask is resized back: the cut's cost grows
    # with the pixel count, its accuracy only with the stone's size in pixels, which is ample here.
    max_working_side: int = 1280
    # The frame's long side the pixel-sized settings above were tuned at (the simulated rig's 320x240).
    # On larger frames the two that follow the stone's size in pixels scale with it (see `for_frame`).
    tuned_side: int = 320

    def for_frame(self, long_side: int) -> "MaskSettings":
        """These settings for a frame whose long side is `long_side` pixels.

        The seed's closing bridges gaps of a size on the stone, and smoothness weighs a pixel of
        boundary against a pixel of area, whose counts grow linearly and quadratically with the
        resolution: both scale with it, so a cut on a finer camera makes the same decisions about
        regions. The settings that follow the pixel itself (mixed edge pixels, noise blur, the
        shadow field's gap) do not scale.
        """
        factor = long_side / self.tuned_side
        # the result is tuned for `long_side` itself, so applying it twice scales once
        return replace(self, seed_closing_px=max(1, round(self.seed_closing_px * factor)),
                       smoothness=self.smoothness * factor, tuned_side=long_side)


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


def column_medians(values: np.ndarray) -> np.ndarray:
    """np.median(values, axis=0) for [N, C], to the bit, in a seventh of the time: numpy selects both middle
    ranks along the strided axis; here one selection per contiguous column and the largest value below it."""
    columns = np.ascontiguousarray(values.T)  # [C, N]
    n = columns.shape[1]
    if n == 0:
        return np.median(values, axis=0)
    k = n // 2
    part = np.partition(columns, k, axis=1)
    if n % 2:
        return part[:, k]
    return ((part[:, :k].max(axis=1) + part[:, k]) / 2).astype(values.dtype)


def plate_matched(shot: np.ndarray, plate: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """The plate scaled to the shot's exposure by a robust per-channel gain on the frame border."""
    border = _border(shot.shape[:2], settings.border_fraction)
    gain = column_medians(shot[border] / np.maximum(plate[border], 1e-4))  # [3]
    return plate * gain.astype(np.float32)


@dataclass(frozen=True)
class RelativeNoise:
    """The noise of a relative cue (a ratio or difference against the plate), measured on the border strip,
    where there is only backdrop. Photon noise makes a relative cue's spread scale as 1/sqrt(signal), so the
    border's spread and offset hold at any plate level; `at` gives them for just the pixels a step reads."""

    reference: np.ndarray  # [C] the border's median plate level
    spread: np.ndarray  # [C] the cue's sigma at that level
    centre: np.ndarray  # [C] the cue's offset at that level

    @staticmethod
    def measure(values: np.ndarray, level: np.ndarray) -> "RelativeNoise":
        """From the cue `values` [B, C] and the plate's `level` [B, C] on the border strip's pixels."""
        reference = column_medians(level)
        scaled = values * _signal(level, reference)  # [B, C]
        centre = column_medians(scaled)
        return RelativeNoise(reference, 1.4826 * column_medians(np.abs(scaled - centre)) + 1e-6, centre)

    def at(self, level: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sigma and offset [..., C] of the cue where the plate's level is `level` [..., C]."""
        signal = _signal(level, self.reference)
        return self.spread / signal, self.centre / signal


def _signal(level: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(level / reference, 1e-3))


def difference_mask(shot: np.ndarray, plate: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """Sure-stone pixels [H, W] bool from shadow-aware plate differencing (sparse on weak stones).

    `plate` is already matched to the shot's exposure.
    """
    eps = 1e-4
    border = _border(shot.shape[:2], settings.border_fraction)
    smooth_s = cv2.GaussianBlur(shot, (0, 0), 1.0)
    smooth_p = cv2.GaussianBlur(plate, (0, 0), 1.0)
    ls, lp = _luma(smooth_s) + eps, _luma(smooth_p) + eps
    log_ratio = np.log(ls / lp)  # [H, W]
    chroma = np.linalg.norm(smooth_s / ls[..., None] - smooth_p / lp[..., None], axis=2)  # [H, W]

    def zscore(values: np.ndarray) -> np.ndarray:
        sigma, centre = RelativeNoise.measure(values[border][:, None], lp[border][:, None]).at(lp[..., None])
        return ((values[..., None] - centre) / sigma)[..., 0]

    n = settings.noise_sigmas
    brighter = (zscore(log_ratio) > n) & (log_ratio > settings.min_ratio_dev)
    too_dark = log_ratio < np.log(settings.shadow_floor)
    chroma_cue = (zscore(chroma) > n) & (chroma > settings.min_chroma_dev)
    opening = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    sure = cv2.morphologyEx((brighter | too_dark | chroma_cue).astype(np.uint8), cv2.MORPH_OPEN, opening)
    return sure.astype(bool)


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
    hull = cv2.convexHull(cv2.findNonZero(seed.astype(np.uint8)))
    return cv2.fillConvexPoly(np.zeros(seed.shape, np.uint8), hull, 1).astype(bool)


def seed_mask(shot: np.ndarray, plate: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """The first guess [H, W] bool: the hull of the sure-stone cues. `plate` is matched to the shot."""
    return seed_from_cues(difference_mask(shot, plate, settings), settings)


def largest_component_filled(mask: np.ndarray) -> np.ndarray:
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return np.zeros_like(mask, dtype=bool)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return fill_holes(labels == biggest)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """`mask` [H, W] with every hole filled, to the pixel as scipy's binary_fill_holes fills it (the background
    4-connected), by one OpenCV flood fill from outside the frame: every shot's seed and every hull needs one."""
    flood = np.pad(mask, 1).astype(np.uint8)
    cv2.floodFill(flood, None, (0, 0), 2, flags=4)
    return flood[1:-1, 1:-1] != 2


def shadow_field(log_ratio: np.ndarray, background: np.ndarray, sigma_px: float) -> np.ndarray:
    """Smooth log darkening [H, W] of the plate, fitted to `background` pixels, 0 where none are near.

    A Gaussian-weighted plane per pixel (local linear regression), so next to the stone, where
    only one side has background, the field continues the shadow's slope instead of flattening
    it. Shadows only darken, so the field is clipped at 0. The moments are filtered in float32,
    which OpenCV does much faster than float64, and solved in float64, where the cancellation is.
    """
    radius = int(np.ceil(4 * sigma_px))
    u = np.arange(-radius, radius + 1, dtype=np.float64)  # neighbour offset from the output pixel
    g = np.exp(-0.5 * (u / sigma_px) ** 2)
    kernels = {order: (u**order * g).astype(np.float32) for order in (0, 1, 2)}
    weight = background.astype(np.float32)  # [H, W]
    # the values' mean is taken out before filtering and added back to the fitted level: float32 then holds
    # their variation instead of their common offset
    offset = float(np.mean(log_ratio[background])) if background.any() else 0.0
    value = np.where(background, log_ratio - offset, 0.0).astype(np.float32)

    def moment(image: np.ndarray, order_x: int, order_y: int) -> np.ndarray:
        return cv2.sepFilter2D(image, cv2.CV_32F, kernels[order_x], kernels[order_y], borderType=cv2.BORDER_CONSTANT)

    weights = [moment(weight, *orders) for orders in ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))]
    values = [moment(value, *orders) for orders in ((0, 0), (1, 0), (0, 1))]
    return _plane_level(*weights, *values, 1e-2 * sigma_px**2, offset)


@njit(cache=True)
def _plane_level(m00, m10, m01, m20, m11, m02, v0, v1, v2, ridge_per_weight, offset):
    """Each pixel's local plane, from its weighted moments [H, W], at the pixel itself, clipped at 0 (float32;
    the solve in float64).

    One pass in place of numpy's thirty over the crop."""
    level = np.zeros(m00.shape, np.float32)
    for y in range(m00.shape[0]):
        for x in range(m00.shape[1]):
            a00 = np.float64(m00[y, x])
            if not a00 > 1e-3:
                continue  # no background near: no shadow
            ridge = ridge_per_weight * a00  # keeps the slope tame where background lies along a line
            a10, a01, a11 = np.float64(m10[y, x]), np.float64(m01[y, x]), np.float64(m11[y, x])
            a20, a02 = np.float64(m20[y, x]) + ridge, np.float64(m02[y, x]) + ridge
            b0, b1, b2 = np.float64(v0[y, x]), np.float64(v1[y, x]), np.float64(v2[y, x])
            # the first unknown of the symmetric 3x3 normal equations, by Cramer's rule
            minor = a20 * a02 - a11 * a11
            det = a00 * minor - a10 * (a10 * a02 - a11 * a01) + a01 * (a10 * a11 - a20 * a01)
            plane = (b0 * minor - a10 * (b1 * a02 - a11 * b2) + a01 * (b1 * a11 - a20 * b2)) / det + offset
            level[y, x] = plane if not plane > 0.0 else 0.0  # shadows only darken
    return level


def colour_model(samples: np.ndarray, bins: int, floor: float) -> Callable[[np.ndarray], np.ndarray]:
    """Negative log density of a smoothed histogram of `samples` [N, 3]; returns a function of [..., 3]."""
    lo, hi = np.percentile(samples, [0.5, 99.5], axis=0)  # [3] each
    pad = 3 * (hi - lo) / bins + 1e-3
    lo, hi = lo - pad, hi + pad
    counts, _ = np.histogramdd(samples, bins=bins, range=list(zip(lo, hi)))
    density = ndimage.gaussian_filter(counts, 1.0) / (len(samples) * np.prod((hi - lo) / bins))

    def nll(values: np.ndarray) -> np.ndarray:
        index = np.floor((values - lo) / (hi - lo) * bins).astype(np.int64)  # [..., 3]
        inside = np.all((index >= 0) & (index < bins), axis=-1)
        index = np.clip(index, 0, bins - 1)
        found = np.where(inside, density[index[..., 0], index[..., 1], index[..., 2]], 0.0)
        return -np.log(found + floor)

    return nll


def min_cut(evidence: np.ndarray, features: np.ndarray, smoothness: float, fixed_background: np.ndarray) -> np.ndarray:
    """Stone labels [H, W] minimising -sum(evidence over stone) + contrast-weighted boundary length.

    `evidence` [H, W] is the log-likelihood ratio stone : background in nats; `features`
    [H, W, C] is where edges are read (8 neighbours, weights as in GrabCut: exp(-beta |df|^2)
    with beta from the mean squared neighbour difference). Solved exactly by max-flow; of the
    minimum cuts, the one with the least stone.
    """
    first, head, sister, residual, terminal = _cut_graph(
        np.ascontiguousarray(evidence, dtype=np.float64), np.ascontiguousarray(features, dtype=np.float32),
        float(smoothness), np.ascontiguousarray(fixed_background, dtype=np.bool_))
    maxflow.max_flow(first, head, sister, residual, terminal)
    return maxflow.source_side(first, head, residual, terminal).reshape(evidence.shape)


# A pixel's 8 neighbours; the arc back from neighbour k is the neighbour's arc 7 - k
_NEIGHBOUR_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_PAIRS = ((0, 1), (1, 0), (1, 1), (1, -1))  # each neighbour pair once, stored at its first pixel in row-major order
# neighbour k's pair as (pixel the pair is stored at, relative to this one; its pair)
_NEIGHBOURS = (((-1, -1), 2), ((-1, 0), 1), ((-1, 1), 3), ((0, -1), 0), ((0, 0), 0), ((0, 0), 3), ((0, 0), 1),
               ((0, 0), 2))


@njit(cache=True)
def _cut_graph(evidence, features, smoothness, fixed_background):
    """The cut's graph for `maxflow`: eight arcs a pixel (a neighbour off the image gets an arc of no
    capacity to itself), int32 capacities, each pixel's terminal capacity stone minus background.

    Each neighbour pair's capacity is worked out once and read by both of its pixels."""
    h, w = evidence.shape
    n = h * w
    squared = np.zeros((h, w, 4), np.float32)
    total, pairs = 0.0, 0
    for y in range(h):
        for x in range(w):
            for k in range(4):
                yy, xx = y + _PAIRS[k][0], x + _PAIRS[k][1]
                if yy < h and 0 <= xx < w:
                    difference = np.float32(0.0)
                    for c in range(features.shape[2]):
                        d = features[y, x, c] - features[yy, xx, c]
                        difference += d * d
                    squared[y, x, k] = difference
                    total += difference
                    pairs += 1
    beta = 1.0 / (2.0 * total / max(pairs, 1) + 1e-12)
    pair_capacity = np.empty((h, w, 4), np.int32)
    for y in range(h):
        for x in range(w):
            for k in range(4):
                distance = 1.0 if _PAIRS[k][0] == 0 or _PAIRS[k][1] == 0 else np.sqrt(2.0)
                weight = _NATS_TO_CAPACITY * smoothness * np.exp(-beta * squared[y, x, k])
                pair_capacity[y, x, k] = np.int32(np.rint(weight / distance)) + 1
    fixed = np.rint(_NATS_TO_CAPACITY * (_MAX_NATS + 8 * smoothness)) + 8
    first = np.arange(0, 8 * n + 1, 8).astype(np.int32)
    head = np.empty(8 * n, np.int32)
    sister = np.empty(8 * n, np.int32)
    residual = np.zeros(8 * n, np.int32)
    terminal = np.empty(n, np.int32)
    for y in range(h):
        for x in range(w):
            i = y * w + x
            for k in range(8):
                a = 8 * i + k
                yy, xx = y + _NEIGHBOUR_OFFSETS[k][0], x + _NEIGHBOUR_OFFSETS[k][1]
                if 0 <= yy < h and 0 <= xx < w:
                    (sy, sx), pair = _NEIGHBOURS[k]
                    head[a] = yy * w + xx
                    sister[a] = 8 * (yy * w + xx) + 7 - k
                    residual[a] = pair_capacity[y + sy, x + sx, pair]
                else:
                    head[a] = i
                    sister[a] = a
            nats = min(max(evidence[y, x], -_MAX_NATS), _MAX_NATS)
            to_stone = np.rint(_NATS_TO_CAPACITY * max(nats, 0.0))
            to_background = fixed if fixed_background[y, x] else np.rint(_NATS_TO_CAPACITY * max(-nats, 0.0))
            terminal[i] = np.int32(to_stone - to_background)
    return first, head, sister, residual, terminal


def chroma_chi2(ratio: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Chi-square [h, w] of each pixel's colour against the plate's, luminance left out (2 dof)."""
    inverse = 1.0 / variance
    luma = (ratio * inverse).sum(axis=2) / inverse.sum(axis=2)
    return ((ratio - luma[..., None]) ** 2 * inverse).sum(axis=2)


def attached(candidates: np.ndarray, region: np.ndarray) -> np.ndarray:
    """The `candidates` [h, w] pixels joined to `region` through other candidates (8-connected)."""
    count, labels = cv2.connectedComponents((candidates | region).astype(np.uint8), connectivity=8)
    joined = np.zeros(count, dtype=bool)
    joined[np.unique(labels[region])] = True
    joined[0] = False
    return candidates & joined[labels]


def matte_boundary(
    shot: np.ndarray, background: np.ndarray, stone: np.ndarray, sigma: np.ndarray, max_alpha_sigma: float
) -> np.ndarray:
    """The stone's coverage [h, w] in [0, 1]: the cut's labels, with the pixels on its boundary unmixed.

    A boundary pixel mixes the stone's colour with the background's, and the cut, which sees only
    which of the two it is closer to, leans towards whichever differs more from the mix: a dark
    stone's edge pixels all went to the stone (a ring of false stone one pixel wide). Here each
    one is unmixed against the shadowed plate behind it (`background`) and the stone colour
    next to it, C = a F + (1 - a) B, solved for a by noise-weighted least squares. Pixels whose
    stone and background are too alike to read a (a's standard error above `max_alpha_sigma`)
    keep the cut's label. A pixel is stone if the stone covers at least half of it, the truth's
    rule too; the fraction itself is what training needs (see `Matte`).
    """
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    inner = cv2.erode(stone.astype(np.uint8), cross).astype(bool)
    band = cv2.dilate(stone.astype(np.uint8), cross).astype(bool) & ~inner
    # the stone's colour at the edge: its pixels within two of the boundary, the pixel itself left out
    # (deeper pixels are shaded differently: a pale stone's rim is darker than its face)
    edge = (stone & ~cv2.erode(inner.astype(np.uint8), cross).astype(bool)).astype(np.float32)  # [h, w]
    offsets = np.arange(-3, 4, dtype=np.float32)
    kernel = np.exp(-0.5 * (offsets[:, None] ** 2 + offsets[None, :] ** 2))
    kernel[3, 3] = 0.0
    weight = cv2.filter2D(edge, -1, kernel, borderType=cv2.BORDER_CONSTANT)
    edge_colour = cv2.filter2D(shot * edge[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT)
    edge_colour /= np.maximum(weight, 1e-6)[..., None]
    scale = np.maximum(background, _LOG_FLOOR)
    mix = (shot - background) / scale  # [h, w, 3] in units of the background, where the noise sigma is known
    pure_stone = (edge_colour - background) / scale
    information = (pure_stone**2 / sigma**2).sum(axis=2)  # [h, w] Fisher information on alpha
    alpha = (mix * pure_stone / sigma**2).sum(axis=2) / np.maximum(information, 1e-12)
    readable = band & (weight > 1e-3) & (information >= max_alpha_sigma**-2)
    return np.where(readable, np.clip(alpha, 0.0, 1.0), stone).astype(np.float32)


def silhouette_prior(silhouette: np.ndarray, settings: MaskSettings, roofed: np.ndarray | None = None) -> np.ndarray:
    """Evidence [H, W] in nats for stone inside a predicted silhouette, short of its edge band; 0 elsewhere.
    Inside its `roofed` part [H, W] bool, if given, the weaker `roof_prior_nats`.

    Only for stone: the other rings' hull can miss what their own masks missed, so it never argues for
    background.
    """
    band = np.ones((2 * settings.silhouette_band_px + 1,) * 2, np.uint8)
    inner = cv2.erode(silhouette.astype(np.uint8), band).astype(bool)
    nats = np.full(silhouette.shape, settings.silhouette_prior_nats, dtype=np.float32)
    if roofed is not None:
        nats[roofed] = settings.roof_prior_nats
    return np.where(inner, nats, 0.0).astype(np.float32)


def refine_graph_cut(
    shot: np.ndarray, plate: np.ndarray, seed: np.ndarray, settings: MaskSettings, prior: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The stone's coverage [H, W] from the seed hull, by an iterated graph cut on a crop (see the module
    docstring), and the background behind it [H, W, 3]: the plate, shadowed where the cut fitted a shadow.

    `plate` is already matched to the shot's exposure; `prior` [H, W] is extra evidence for stone, in nats.
    """
    if not seed.any():
        return seed.astype(np.float32), plate
    border = _border(shot.shape[:2], settings.border_fraction)
    ys, xs = np.nonzero(seed)
    h, w = seed.shape
    my = int((ys.max() - ys.min() + 1) * settings.crop_margin) + 4
    mx = int((xs.max() - xs.min() + 1) * settings.crop_margin) + 4
    crop = (slice(max(0, ys.min() - my), min(h, ys.max() + my + 1)),
            slice(max(0, xs.min() - mx), min(w, xs.max() + mx + 1)))
    # The cues are read on the crop alone, their noise on the border strip. The plate is not blurred against
    # the sharp shot: the backdrop is smooth, but a colour chart beside the stone is not, and a blurred plate
    # makes every chart edge look like stone. Its noise is in `sigma`.

    def log_ratio(region: np.ndarray | tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
        log_shot = np.log(np.maximum(shot[region], _LOG_FLOOR))
        return log_shot, log_shot - np.log(np.maximum(plate[region], _LOG_FLOOR))

    colours, ratio = log_ratio(crop)  # [h, w, 3] each
    sigma, centre = RelativeNoise.measure(log_ratio(border)[1], plate[border]).at(plate[crop])
    ratio -= centre
    blur = settings.contrast_blur_px
    shot_b, plate_b = cv2.GaussianBlur(shot, (0, 0), blur), cv2.GaussianBlur(plate, (0, 0), blur)

    def relative(region: np.ndarray | tuple[slice, slice]) -> np.ndarray:
        return (shot_b[region] - plate_b[region]) / np.maximum(plate_b[region], _LOG_FLOOR)

    edge_sigma, edge_centre = RelativeNoise.measure(relative(border), plate_b[border]).at(plate_b[crop])
    edge_contrast = relative(crop) - edge_centre  # [h, w, 3]
    variance = sigma**2 + settings.shadow_slack**2
    inverse = 1.0 / sigma**2
    luma_ratio = (ratio * inverse).sum(axis=2) / inverse.sum(axis=2)  # [h, w] noise-weighted mean over channels
    background_cost_const = 0.5 * np.log(2 * np.pi * variance).sum(axis=2)
    hull_prior = settings.hull_prior_nats * seed[crop]
    if prior is not None:
        hull_prior = hull_prior + prior[crop]
    frame = np.ones(luma_ratio.shape, dtype=bool)
    frame[1:-1, 1:-1] = False
    gap = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.shadow_field_gap_px + 1,) * 2)
    field_px = max(settings.min_shadow_field_px, settings.shadow_field_fraction * float(np.sqrt(seed.sum())))
    stone = seed[crop]
    plate_coloured = chroma_chi2(ratio, variance) < settings.plate_chroma_chi2

    def fitted_shadow(stone: np.ndarray) -> np.ndarray:
        near_stone = cv2.dilate(stone.astype(np.uint8), gap).astype(bool)
        background = ~near_stone
        shadow = shadow_field(luma_ratio, background, field_px)
        if plate_coloured[stone].mean() <= settings.max_plate_coloured_stone:
            # the stone's own colour tells it apart, so plate-coloured pixels next to it in a shadow
            # are the shadow's steep, darkest part, which the plane would otherwise never see
            in_shadow = shadow < np.log1p(-settings.min_ratio_dev)
            background |= attached(plate_coloured & near_stone & in_shadow, background)
            shadow = shadow_field(luma_ratio, background, field_px)
        return shadow

    shadow = None  # fitted to `stone` as it is, once a round has fitted it
    for _ in range(settings.cut_iterations):
        if not stone.any():
            break
        shadow = fitted_shadow(stone)
        background_nll = 0.5 * ((ratio - shadow[..., None]) ** 2 / variance).sum(axis=2) + background_cost_const
        stone_nll = colour_model(colours[stone], settings.colour_bins, settings.colour_floor)(colours)
        # in noise units against the shadowed plate: the plate's edges and the shadow's gradient cancel
        edges = (edge_contrast - np.expm1(shadow)[..., None]) / edge_sigma  # [h, w, 3]
        cut = min_cut(background_nll - stone_nll + hull_prior, edges, settings.smoothness, frame)
        moved = int(np.count_nonzero(cut != stone))
        if moved == 0:
            break  # a fixed point: every further round would cut the same
        stone, shadow = cut, None
        if moved <= settings.settled_fraction * np.count_nonzero(stone):
            break
    coverage = np.zeros(seed.shape, dtype=np.float32)
    background = plate.copy()
    coverage[crop] = stone
    if stone.any():
        background[crop] *= np.exp(fitted_shadow(stone) if shadow is None else shadow)[..., None]
        if settings.matte_boundary:
            coverage[crop] = matte_boundary(shot[crop], background[crop], stone, sigma, settings.max_alpha_sigma)
    return coverage, background


@dataclass
class Matte:
    """A shot split into the stone's coverage and its own colour.

    Training renders the stone alone on black, so what it should match at an edge pixel is the
    stone's colour times its coverage, alpha F, not the shot, which also holds (1 - alpha) of the
    plate there, a share no model consistent across views can fit.
    """

    alpha: np.ndarray  # [H, W] float32 in [0, 1]: the stone's coverage, fractional only on the mask's edge
    foreground: np.ndarray  # [H, W, 3] float32 linear: the stone's colour (`unmix`) where 0 < alpha < 1, else the shot

    @property
    def mask(self) -> np.ndarray:
        """[H, W] bool: the stone covers at least half of the pixel (one component, holes filled)."""
        return self.alpha >= 0.5

    def downscaled(self, width: int) -> "Matte":
        """The matte area-averaged to `width` pixels wide (the training resolution); itself if not wider.

        Cut at the camera's resolution and averaged down, the coverage of a training pixel is the share of
        its sub-pixels the stone covers: a stone's one-pixel rim of doubtful coverage shrinks with the pixel,
        where a cut at the training resolution itself has no finer evidence to go on. The colour averaged is
        the stone's alone (premultiplied by coverage), so an edge pixel's colour stays a mix of the stone's
        colours under it, unmixed from the plate.
        """
        h, w = self.alpha.shape
        if width >= w:
            return self
        size = (width, max(1, round(h * width / w)))

        def area(image: np.ndarray) -> np.ndarray:
            return cv2.resize(image, size, interpolation=cv2.INTER_AREA)

        coverage = area(self.alpha)
        premultiplied = area(self.foreground * self.alpha[..., None])
        alpha = _one_stone(coverage)
        partial = (alpha > 0.0) & (alpha < 1.0)
        unmixed = premultiplied / np.maximum(coverage, 1e-6)[..., None]
        foreground = np.where(partial[..., None], unmixed, area(self.foreground)).astype(np.float32)
        return Matte(alpha=alpha, foreground=foreground)


def _one_stone(coverage: np.ndarray) -> np.ndarray:
    """Coverage [H, W] reduced to one stone: the largest component of the pixels at least half covered,
    holes filled (they are stone), and partial coverage kept only on its edge, where it is below one half
    (a ring pixel covered more would have joined the component): so mask == alpha >= 0.5."""
    mask = largest_component_filled(coverage >= 0.5)
    ring = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask
    return np.where(mask, np.where(coverage >= 0.5, coverage, 1.0), np.where(ring, coverage, 0.0)).astype(np.float32)


def compute_matte(
    shot_linear: np.ndarray,
    plate_linear: np.ndarray,
    settings: MaskSettings = MaskSettings(),
    silhouette: np.ndarray | None = None,
    roofed: np.ndarray | None = None,
) -> Matte:
    """Mask, coverage and unmixed colour of a developed shot against the clean plate of the same elevation.

    `silhouette` [H, W] bool, when given, is where other views put the stone (cross_view.py): it joins the
    seed, so the stone's colour model also learns the stone's shaded side, and it weighs in the cut. Its
    `roofed` part [H, W] bool, when given, may be a roof over the stone and weighs less (`roof_prior_nats`).
    """
    if shot_linear.shape != plate_linear.shape or shot_linear.ndim != 3 or shot_linear.shape[2] != 3:
        raise BadInputError(
            f"shot {shot_linear.shape} and plate {plate_linear.shape} must be matching [H, W, 3] images"
        )
    for name, region in (("silhouette", silhouette), ("roofed part", roofed)):
        if region is not None and region.shape != shot_linear.shape[:2]:
            raise BadInputError(f"{name} {region.shape} does not match the shot {shot_linear.shape[:2]}")
    full_shot, plate = shot_linear.astype(np.float32), plate_linear.astype(np.float32)
    h, w = full_shot.shape[:2]
    scale = settings.max_working_side / max(h, w)
    shot = full_shot
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        shot, plate = (cv2.resize(image, size, interpolation=cv2.INTER_AREA) for image in (shot, plate))
    settings = settings.for_frame(max(shot.shape[:2]))
    plate = plate_matched(shot, plate, settings)
    seed, prior = seed_mask(shot, plate, settings), None
    if silhouette is not None:
        if scale < 1.0:
            def at_working_size(region: np.ndarray) -> np.ndarray:
                return cv2.resize(region.astype(np.uint8), shot.shape[1::-1], interpolation=cv2.INTER_NEAREST).astype(bool)

            silhouette = at_working_size(silhouette)
            roofed = None if roofed is None else at_working_size(roofed)
        seed, prior = seed | silhouette.astype(bool), silhouette_prior(silhouette, settings, roofed)
    coverage, background = refine_graph_cut(shot, plate, seed, settings, prior)
    if scale < 1.0:
        coverage, background = (cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
                                for image in (coverage, background))
    alpha = _one_stone(coverage)
    return Matte(alpha=alpha, foreground=unmix(full_shot, background, alpha, settings))


def nearby_stone_colour(shot: np.ndarray, solid: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and variance [H, W, 3] of the `solid` stone pixels near each pixel (Gaussian weights of scale
    `sigma_px`), and the weight [H, W] they had."""
    radius = int(np.ceil(3 * sigma_px))
    offsets = np.arange(-radius, radius + 1, dtype=np.float32)
    kernel = np.exp(-0.5 * (offsets[:, None] ** 2 + offsets[None, :] ** 2) / sigma_px**2)

    def smooth(image: np.ndarray) -> np.ndarray:
        return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_CONSTANT)

    inside = solid.astype(np.float32)
    weight = smooth(inside)
    norm = np.maximum(weight, 1e-6)[..., None]
    mean = smooth(shot * inside[..., None]) / norm
    variance = np.maximum(smooth(shot**2 * inside[..., None]) / norm - mean**2, 0.0)
    return mean, variance, weight


def unmix(shot: np.ndarray, background: np.ndarray, alpha: np.ndarray, settings: MaskSettings) -> np.ndarray:
    """The stone's own colour [H, W, 3]: the shot where the stone covers the pixel or is absent, and on its
    partly covered edge the most probable colour given the mix C = a F + (1 - a) B and the stone beside it.

    Solving the mix for F alone divides the shot's noise and the background model's error by a, which at small
    coverage makes colours neither stone nor plate has. Here F also has a prior, the colour of the solid stone
    pixels nearby (mean and spread, per channel), so the less of a pixel the stone covers the more its colour
    is the stone's nearby one (the maximum a posteriori estimate of Bayesian matting with the coverage known).
    """
    colour = shot.astype(np.float32)
    partial = (alpha > 0.0) & (alpha < 1.0)
    if not partial.any():
        return colour
    solid = alpha >= 1.0
    fallback = shot[solid if solid.any() else partial].mean(axis=0)  # a stone with no solid pixel near
    ys, xs = np.nonzero(partial)
    pad = int(np.ceil(3 * settings.edge_colour_px)) + 1
    box = (slice(max(0, ys.min() - pad), ys.max() + pad + 1), slice(max(0, xs.min() - pad), xs.max() + pad + 1))
    border = _border(shot.shape[:2], settings.border_fraction)
    on_border, level = shot[border], np.maximum(background[border], _LOG_FLOOR)
    noise = RelativeNoise.measure(np.log(np.maximum(on_border, _LOG_FLOOR)) - np.log(level), level)
    sigma = noise.at(np.maximum(background[box], _LOG_FLOOR))[0]
    c, b, a = shot[box], background[box], alpha[box][..., None]
    prior, spread, weight = nearby_stone_colour(c, solid[box], settings.edge_colour_px)
    known = (weight > 1e-3)[..., None]
    prior = np.where(known, prior, fallback)
    prior_var = np.where(known, spread, 0.0) + (settings.edge_colour_floor * np.maximum(prior, _LOG_FLOOR)) ** 2
    mix_var = (sigma**2 + settings.shadow_slack**2) * np.maximum(b, _LOG_FLOOR) ** 2
    residual = c - (1.0 - a) * b  # a F plus noise
    estimate = (a * residual / mix_var + prior / prior_var) / (a * a / mix_var + 1.0 / prior_var)
    colour[box] = np.where(partial[box][..., None], np.maximum(estimate, 0.0), c)
    return colour


def compute_mask(
    shot_linear: np.ndarray,
    plate_linear: np.ndarray,
    settings: MaskSettings = MaskSettings(),
    silhouette: np.ndarray | None = None,
    roofed: np.ndarray | None = None,
) -> np.ndarray:
    """Stone mask [H, W] bool for a developed shot and the clean plate of the same elevation."""
    return compute_matte(shot_linear, plate_linear, settings, silhouette, roofed).mask


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
