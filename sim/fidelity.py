"""How faithful a scan's training views are to what the sensor saw: the one definition bench and tests use.

Each training view (images/<stem>.png, the stone's colour, and masks/<stem>.png, its coverage) is scored
against the truth image of its shot (sim/truth.py) at the training size, in display-encoded sRGB, the
values training fits:
- on the stone (the true mask shrunk by `BAND_PX`) and in the silhouette band (within `BAND_PX` of the true
  mask's edge), the training target, colour times coverage (View.target), against the true stone alone on
  black, its colour times its true coverage: PSNR, and on the stone the mean CIEDE2000;
- on the plate (everything further out), the image against the exposed image: PSNR;
- false colour: the silhouette's pixels (within `BAND_PX` of the true or the training mask's edge) that hold
  some stone and whose saturation (max - min of RGB) is above both `FALSE_COLOUR_FLOOR` and
  `FALSE_COLOUR_FACTOR` times the 99th percentile of the stone's own: a colour neither stone nor plate has.
The develop's exposure and white are arbitrary up to a gain per channel, so the truth is first scaled by the
median ratio of image to truth on the plate: what is scored is the matte, the unmixing and the noise.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sim.sensor import SRGB_TO_XYZ
from sim.truth import TruthImage, true_images_at
from station.errors import BadInputError
from station.process.images_io import linear_to_srgb, read_png16
from station.scanfolder import ScanFolder

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # colour warns at import that matplotlib is absent
    import colour

BAND_PX = 2
FALSE_COLOUR_FLOOR = 60 / 255
FALSE_COLOUR_FACTOR = 3.0
REGIONS = ("stone", "band", "plate")
_D65_XY = np.array([0.3127, 0.3290])


@dataclass
class ViewFidelity:
    """One view's sums, so a ring's figures pool its pixels rather than average its views' ratios."""

    name: str
    squared_error: dict[str, float]  # region -> sum over its pixels and channels
    values: dict[str, int]  # region -> pixels x channels
    delta_e_sum: float
    delta_e_pixels: int
    false_colour: int
    iou: float  # the training mask (coverage >= 1/2) against the true one

    def psnr(self, region: str) -> float:
        return psnr(self.squared_error[region], self.values[region])


def psnr(squared_error: float, values: int) -> float:
    """PSNR in dB of values in [0, 1]; inf for no error."""
    mse = squared_error / max(values, 1)
    return float("inf") if mse <= 0.0 else float(10.0 * np.log10(1.0 / mse))


def _grow(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)).astype(bool)


def _shrink(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8), borderValue=0).astype(bool)


def silhouette_band(mask: np.ndarray, px: int = BAND_PX) -> np.ndarray:
    """[H, W] bool: pixels within `px` (chessboard distance) of the mask's edge, on either side."""
    return _grow(mask, px) & ~_shrink(mask, px)


def saturation(display: np.ndarray) -> np.ndarray:
    """[H, W] max - min of display-encoded RGB [H, W, 3]."""
    return display.max(axis=2) - display.min(axis=2)


def false_colour_pixels(display: np.ndarray, coverage: np.ndarray, true_mask: np.ndarray) -> int:
    """Silhouette pixels of a training view (display RGB [H, W, 3], coverage [H, W]) with a colour neither the
    stone nor the plate has (see the module docstring)."""
    interior = _shrink(true_mask, BAND_PX)
    if not interior.any():
        return 0
    sat = saturation(display)
    limit = max(FALSE_COLOUR_FLOOR, FALSE_COLOUR_FACTOR * float(np.percentile(sat[interior], 99)))
    band = silhouette_band(true_mask) | silhouette_band(coverage >= 0.5)
    return int((band & (coverage > 0) & (sat > limit)).sum())


def _lab(linear: np.ndarray) -> np.ndarray:
    return colour.XYZ_to_Lab(np.clip(linear, 0.0, None) @ SRGB_TO_XYZ.T, _D65_XY)


def view_fidelity(name: str, image: np.ndarray, coverage: np.ndarray, truth: TruthImage) -> ViewFidelity:
    """Score one training view: `image` [H, W, 3] linear (as images/ decodes), `coverage` [H, W] in [0, 1]."""
    if image.shape[:2] != coverage.shape or coverage.shape != truth.alpha.shape:
        raise BadInputError(f"{name}: image {image.shape}, mask {coverage.shape} and truth {truth.alpha.shape} differ")
    true_mask = truth.alpha >= 0.5
    plate = ~_grow(true_mask, BAND_PX)
    lit = plate & (truth.exposed.min(axis=2) > 1e-3)
    gain = np.median(image[lit] / truth.exposed[lit], axis=0) if lit.any() else np.ones(3)  # [3]
    exposed, stone = truth.exposed * gain, truth.stone * gain
    display = linear_to_srgb(image)
    true_colour = stone / np.maximum(truth.alpha, 1e-6)[..., None]
    true_target = linear_to_srgb(true_colour) * truth.alpha[..., None]
    target = display * coverage[..., None]
    interior, band = _shrink(true_mask, BAND_PX), silhouette_band(true_mask)
    errors = {"stone": (target - true_target)[interior], "band": (target - true_target)[band],
              "plate": (display - linear_to_srgb(exposed))[plate]}
    delta_e = colour.delta_E(_lab(image[interior]), _lab(exposed[interior]), method="CIE 2000")
    mask = coverage >= 0.5
    union = float((mask | true_mask).sum())
    return ViewFidelity(
        name=name,
        squared_error={r: float(np.square(e, dtype=np.float64).sum()) for r, e in errors.items()},
        values={r: int(e.size) for r, e in errors.items()},
        delta_e_sum=float(np.sum(delta_e)), delta_e_pixels=int(np.size(delta_e)),
        false_colour=false_colour_pixels(display, coverage, true_mask),
        iou=float((mask & true_mask).sum() / union) if union else 1.0,
    )


def ring_summary(views: list[ViewFidelity]) -> dict:
    """A ring's figures: PSNR per region over its pooled pixels, mean dE00 on the stone, false colour."""
    pooled = {r: psnr(sum(v.squared_error[r] for v in views), sum(v.values[r] for v in views)) for r in REGIONS}
    counts = [v.false_colour for v in views]
    return {
        "views": len(views),
        **{f"psnr_{r}_db": round(pooled[r], 2) for r in REGIONS},
        "delta_e00_stone": round(sum(v.delta_e_sum for v in views) / max(sum(v.delta_e_pixels for v in views), 1), 3),
        "false_colour_per_view": round(float(np.mean(counts)), 2) if counts else 0.0,
        "false_colour_max": max(counts, default=0),
        "iou_mean": round(float(np.mean([v.iou for v in views])), 4) if views else 0.0,
    }


def read_coverage(path: Path) -> np.ndarray:
    """A masks/ PNG as coverage [H, W] in [0, 1] (masks hold fractions on the stone's edge)."""
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.ndim != 2:
        raise BadInputError(f"{path}: missing or not a one-channel mask")
    return data.astype(np.float32) / float(np.iinfo(data.dtype).max)


def scan_fidelity(scan: ScanFolder) -> dict[float, list[ViewFidelity]]:
    """Every developed shot of a simulated scan scored against its truth, by ring (elevation)."""
    shots = [e for e in scan.read_manifest() if e.kind == "shot" and (scan.masks_dir / f"{Path(e.file).stem}.png").is_file()]
    rings: dict[float, list[ViewFidelity]] = {}
    if not shots:
        return rings
    width = read_coverage(scan.masks_dir / f"{Path(shots[0].file).stem}.png").shape[1]
    truths = true_images_at(scan.root, width, [e.file for e in shots])
    for entry in shots:
        stem = Path(entry.file).stem
        image = read_png16(scan.images_dir / f"{stem}.png")
        rings.setdefault(entry.elevation_deg, []).append(
            view_fidelity(stem, image, read_coverage(scan.masks_dir / f"{stem}.png"), truths[entry.file]))
    return dict(sorted(rings.items()))
