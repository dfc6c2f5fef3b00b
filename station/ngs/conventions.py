"""The rasteriser's fixed conventions (gsplat's), defined once for the kernels, the reference and the exporters.

A model trained here must render the same in gsplat and in any INRIA-layout viewer, so these values are
not tuning knobs: every module that composites, projects or converts colour imports them from here.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

TILE = 16  # pixels per tile side
EPS2D = 0.3  # px^2 low-pass added to every projected 2D covariance
ALPHA_MAX = 0.99  # a Gaussian never composites fully opaque
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
T_STOP = 1e-4  # stop before a Gaussian that would bring transmittance to this or less

# Real spherical-harmonic basis constants up to degree 3, in 3DGS's sign convention.
SH_C0 = 0.28209479177387814  # Y_0^0: colour = SH_C0 * dc + 0.5
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

Colour = TypeVar("Colour", torch.Tensor, np.ndarray, float)


def rgb_to_sh(rgb: Colour) -> Colour:
    """RGB in [0, 1] -> the DC SH coefficient that renders it (tensor, array or number alike)."""
    return (rgb - 0.5) / SH_C0

