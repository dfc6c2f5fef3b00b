"""The simulated camera's lens: Brown-Conrady distortion, vignetting and per-shot exposure jitter.

Each effect acts where it does in a real camera: distortion decides where each sensor pixel looks
(sim/scene.py casts its rays through `SimLens.pixel_directions`), while vignetting and the shutter's
exposure error scale the light reaching the sensor before shot noise and quantisation
(sim/sensor.py). All three are on by default so the pipeline always faces them; `SimLens.ideal()`
is the pinhole camera with a perfect shutter, for tests that need one.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from station.errors import BadInputError

_ITERATE = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class SimLens:
    """Lens and shutter of the simulated camera; each effect has its own switch."""

    distortion: bool = True
    k1: float = -0.10  # a kit zoom at its wide end (OpenCV / COLMAP OPENCV convention, normalised coordinates)
    k2: float = 0.02
    p1: float = 0.0006
    p2: float = -0.0004
    vignetting: bool = True
    corner_falloff_stops: float = 0.6  # light lost at the image corners
    exposure_jitter: bool = True
    exposure_sigma: float = 0.03  # standard deviation of the log gain of each shot (shutter and aperture scatter)

    @staticmethod
    def ideal() -> "SimLens":
        """A pinhole with no falloff and an exact shutter."""
        return SimLens(distortion=False, vignetting=False, exposure_jitter=False)

    def coefficients(self) -> tuple[float, float, float, float]:
        """(k1, k2, p1, p2) as the camera has them: zeros with distortion off."""
        return (self.k1, self.k2, self.p1, self.p2) if self.distortion else (0.0, 0.0, 0.0, 0.0)

    def to_dict(self) -> dict[str, float]:
        return dict(zip(("k1", "k2", "p1", "p2"), self.coefficients()))

    def pixel_directions(self, k: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Normalised pinhole coordinates [N, 2] that the sensor positions (xs, ys) [N] see through this lens.

        Positions use the pixel-centre-at-+0.5 convention of K; OpenCV's (centres at integers) is
        half a pixel off, so K's principal point is moved for it.
        """
        if not self.distortion:
            return np.column_stack([(xs - k[0, 2]) / k[0, 0], (ys - k[1, 2]) / k[1, 1]])
        cv_k = np.array(k, dtype=np.float64)
        cv_k[:2, 2] -= 0.5
        pts = np.column_stack([xs - 0.5, ys - 0.5]).astype(np.float64).reshape(-1, 1, 2)
        out = cv2.undistortPoints(pts, cv_k, np.array(self.coefficients()), R=None, P=None, criteria=_ITERATE)
        return out.reshape(-1, 2)

    @lru_cache(maxsize=8)
    def falloff(self, height: int, width: int) -> np.ndarray:
        """[H, W] share of the light that reaches each pixel: 1 on the axis, `corner_falloff_stops` down at the
        corners, in the shape of the cos^4 law, (1 + c rho^2)^-2 over the radius rho to the corner.

        Read-only and cached: every shot of a scan exposes through the same falloff."""
        if not self.vignetting:
            share = np.ones((height, width))
        elif self.corner_falloff_stops < 0:
            raise BadInputError(f"vignetting of {self.corner_falloff_stops} stops: must not brighten the corners")
        else:
            ys = np.arange(height) + 0.5 - height / 2.0
            xs = np.arange(width) + 0.5 - width / 2.0
            rho2 = (ys[:, None] ** 2 + xs[None, :] ** 2) / ((height / 2.0) ** 2 + (width / 2.0) ** 2)
            share = (1.0 + (2.0 ** (self.corner_falloff_stops / 2.0) - 1.0) * rho2) ** -2
        share.flags.writeable = False
        return share

    def shot_gain(self, rng: np.random.Generator) -> float:
        """This shot's exposure error as a gain on the light (1 with jitter off); drawn from the shot's generator."""
        return float(np.exp(self.exposure_sigma * rng.standard_normal())) if self.exposure_jitter else 1.0
