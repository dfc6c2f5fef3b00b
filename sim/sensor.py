"""A Bayer camera for the simulated rig: what turns scene radiance into a 16-bit raw mosaic.

The chain is the physical one, so the develop stage faces real problems: the camera's RGB is not
sRGB (a non-identity XYZ->camera matrix, with weak red and blue), the lens vignettes and each
shot's exposure is a little off (sim/lens.py), photons arrive as Poisson shot noise, the readout
adds Gaussian noise on a black level, and highlights clip at the white level. Everything random
comes from the caller's generator, so a seed fixes a frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.lens import SimLens
from station.errors import BadInputError

# linear sRGB (D65) -> CIE XYZ, IEC 61966-2-1
SRGB_TO_XYZ = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
D65_WHITE_XYZ = SRGB_TO_XYZ.sum(axis=1)  # XYZ of linear sRGB (1, 1, 1)

# A plausible XYZ->camera matrix (rows R, G, B): broad overlapping dyes, weak red and blue response.
# Scaled so that the D65 white gives a green response of exactly 1, as DNG ColorMatrix1 usually is.
_XYZ_TO_CAMERA = np.array([[0.92, -0.22, -0.14], [-0.42, 1.28, 0.16], [0.02, -0.10, 0.62]])


def _default_xyz_to_camera() -> np.ndarray:
    return _XYZ_TO_CAMERA / (_XYZ_TO_CAMERA @ D65_WHITE_XYZ)[1]


@dataclass
class SensorModel:
    """Sensor and lens constants. Gains are DN per electron at ISO 100; ISO scales the analogue gain."""

    xyz_to_camera: np.ndarray = field(default_factory=_default_xyz_to_camera)  # [3, 3], DNG ColorMatrix1
    black_level: int = 512
    white_level: int = 16383  # 14-bit data in a 16-bit container
    full_well_e: float = 30000.0  # electrons that fill the range at ISO 100
    # electrons per (unit camera-RGB radiance x second) at ISO 100: 1/30 s puts the backdrop near 40% of range
    electrons_per_radiance_s: float = 6.0e5
    read_noise_dn: float = 2.0
    lens: SimLens = field(default_factory=SimLens)  # its vignetting and the shutter's jitter act here

    def camera_neutral(self) -> np.ndarray:
        """[3] camera RGB of a D65 white, green = 1: the DNG AsShotNeutral under the softbox."""
        neutral = self.xyz_to_camera @ D65_WHITE_XYZ
        return neutral / neutral[1]

    def radiance_to_camera(self, radiance: np.ndarray) -> np.ndarray:
        """[H, W, 3] linear sRGB radiance -> [H, W, 3] camera RGB radiance."""
        return radiance @ (self.xyz_to_camera @ SRGB_TO_XYZ).T

    def vignetting(self, height: int, width: int) -> np.ndarray:
        """[H, W] the lens's falloff, 1 on the optical axis."""
        return self.lens.falloff(height, width)

    def expose(self, radiance: np.ndarray, exposure_s: float, iso: float, rng: np.random.Generator) -> np.ndarray:
        """[H, W, 3] linear sRGB radiance -> [H, W] uint16 RGGB mosaic with noise, black level and clipping."""
        if radiance.ndim != 3 or radiance.shape[2] != 3:
            raise BadInputError(f"radiance must be [H, W, 3], got {radiance.shape}")
        height, width = radiance.shape[:2]
        if height % 2 or width % 2:
            raise BadInputError(f"an RGGB mosaic needs even dimensions, got {width}x{height}")
        if not (exposure_s > 0.0 and np.isfinite(exposure_s)):
            raise BadInputError(f"exposure {exposure_s} s must be positive")
        if not (25 <= iso <= 204800):
            raise BadInputError(f"ISO {iso} is outside 25..204800")
        light = self.vignetting(height, width) * self.lens.shot_gain(rng)  # [H, W]
        camera = self.radiance_to_camera(radiance) * light[:, :, None]
        mosaic = bayer_sample(np.clip(camera, 0.0, None))  # [H, W]
        electrons = rng.poisson(mosaic * self.electrons_per_radiance_s * exposure_s).astype(np.float64)
        gain = (self.white_level - self.black_level) / self.full_well_e * (iso / 100.0)  # DN per electron
        signal = self.black_level + electrons * gain + rng.normal(0.0, self.read_noise_dn, size=electrons.shape)
        return np.clip(np.rint(signal), 0, self.white_level).astype(np.uint16)


def bayer_sample(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] -> [H, W] keeping each pixel's RGGB filter colour (R at (0,0), B at (1,1))."""
    mosaic = rgb[:, :, 1].copy()
    mosaic[0::2, 0::2] = rgb[0::2, 0::2, 0]
    mosaic[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return mosaic
