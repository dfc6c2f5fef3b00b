"""The splat's own opacity as a 3D field, whose 0.5 level set is the mesh's surface.

Each Gaussian's opacity at a point x is min(o exp(-(x-mu)^T Sigma^-1 (x-mu) / 2), 0.99), the value the
rasteriser composites where its ray passes through x; the field is 1 - prod(1 - alpha_i(x)). Its
0.5 level set is where the splat turns opaque, as in Gaussian Opacity Fields. It is the mesher's
default because rendered depth, expected or median, reports Gaussian centres, which sit about one
Gaussian scale inside the visible boundary (bench/mesh.py compares the two).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from station.export.splat_model import SplatModel
from station.ngs.conventions import ALPHA_MAX, ALPHA_MIN

LOWPASS_VOXELS = 0.3  # std. dev. added to every Gaussian, in voxels


def inverse_covariances(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """[N, 3] linear scales and [N, 4] wxyz quaternions -> [N, 3, 3] inverse covariances R S^-2 R^T."""
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=1).reshape(-1, 3, 3)
    return np.einsum("nij,nj,nkj->nik", rot, 1.0 / scales**2, rot)


@njit(cache=True)
def _interval(q2, q1, q0, limit):
    """[lo, hi] where q2 t^2 + 2 q1 t + q0 <= limit (q2 > 0), padded for rounding; (1, 0) when empty."""
    centre = -q1 / q2
    room = limit - (q0 + q1 * centre)  # the minimum is at the centre
    if room < 0.0:
        return 1.0, 0.0
    half = math.sqrt(room / q2) * (1.0 + 1e-6) + 1e-12
    return centre - half, centre + half


@njit(parallel=True, cache=True)
def _transmittance(means, inv_cov, opacity, reach, origin, voxel, nx, ny, nz):
    """prod_i (1 - alpha_i) at every voxel centre; one x-slab per thread, Gaussians in a fixed order. A product,
    not a sum of log1p: one libm call a voxel fewer, and where it underflows the voxel is opaque anyway.

    Each Gaussian visits only the voxels of its alpha >= ALPHA_MIN ellipsoid: per slab the (y) range of its
    ellipse, per row the (z) range of its chord, bounded by `reach` as well: a flat disc on the surface skips
    the rest of the cube its largest axis spans, where alpha stays below ALPHA_MIN."""
    out = np.ones((nx, ny, nz))
    for ix in prange(nx):
        px = origin[0] + ix * voxel
        for i in range(means.shape[0]):
            dx = px - means[i, 0]
            r = reach[i]
            if abs(dx) > r:
                continue
            a, b, c = inv_cov[i, 0, 0], inv_cov[i, 0, 1], inv_cov[i, 0, 2]
            d, e, f = inv_cov[i, 1, 1], inv_cov[i, 1, 2], inv_cov[i, 2, 2]
            limit = 2.0 * math.log(opacity[i] / ALPHA_MIN)
            y_lo, y_hi = means[i, 1] - r, means[i, 1] + r
            schur = d - e * e / f  # m minimised over dz is a quadratic in dy with this leading coefficient
            if f > 0.0 and schur > 1e-12 * d:
                lo, hi = _interval(schur, (b - c * e / f) * dx, (a - c * c / f) * dx * dx, limit)
                y_lo, y_hi = max(y_lo, means[i, 1] + lo), min(y_hi, means[i, 1] + hi)
            j0 = max(0, int(math.ceil((y_lo - origin[1]) / voxel)))
            j1 = min(ny - 1, int(math.floor((y_hi - origin[1]) / voxel)))
            for j in range(j0, j1 + 1):
                dy = origin[1] + j * voxel - means[i, 1]
                z_lo, z_hi = means[i, 2] - r, means[i, 2] + r
                if f > 0.0:
                    lo, hi = _interval(f, c * dx + e * dy, a * dx * dx + 2.0 * b * dx * dy + d * dy * dy, limit)
                    z_lo, z_hi = max(z_lo, means[i, 2] + lo), min(z_hi, means[i, 2] + hi)
                k0 = max(0, int(math.ceil((z_lo - origin[2]) / voxel)))
                k1 = min(nz - 1, int(math.floor((z_hi - origin[2]) / voxel)))
                for k in range(k0, k1 + 1):
                    dz = origin[2] + k * voxel - means[i, 2]
                    m = a * dx * dx + d * dy * dy + f * dz * dz + 2.0 * (b * dx * dy + c * dx * dz + e * dy * dz)
                    alpha = min(opacity[i] * math.exp(-0.5 * m), ALPHA_MAX)
                    if alpha >= ALPHA_MIN:
                        out[ix, j, k] *= 1.0 - alpha
    return out


def opacity_field(model: SplatModel, origin: np.ndarray, voxel: float, shape: tuple[int, int, int]) -> np.ndarray:
    """The splat's opacity 1 - prod(1 - alpha_i) at the centres of a voxel grid -> [X, Y, Z] in [0, 1)."""
    opacity = model.opacity().astype(np.float64)
    # The grid samples the field at voxel centres: a Gaussian thinner than a voxel (a flat disc on the
    # surface) would slip between them. Widening each by 0.3 voxel, as the rasteriser's 0.3 px
    # low-pass does on screen, keeps it visible to the grid at a small cost in volume.
    scales = np.sqrt(np.exp(2.0 * model.scales_log.astype(np.float64)) + (LOWPASS_VOXELS * voxel) ** 2)
    visible = opacity > ALPHA_MIN  # a Gaussian below ALPHA_MIN everywhere adds nothing
    opacity, scales = opacity[visible], scales[visible]
    # alpha falls to ALPHA_MIN at Mahalanobis radius sqrt(2 ln(o / ALPHA_MIN)); the largest axis bounds it in space
    reach = scales.max(axis=1) * np.sqrt(2.0 * np.log(opacity / ALPHA_MIN))
    transmittance = _transmittance(model.means[visible].astype(np.float64),
                                   inverse_covariances(scales, model.quats[visible].astype(np.float64)),
                                   opacity, reach, np.asarray(origin, np.float64), float(voxel), *shape)
    return 1.0 - transmittance
