"""The splat's opacity field on a voxel grid against a dense numpy evaluation of every Gaussian at every voxel."""

from __future__ import annotations

import numpy as np

from station.export.opacity_field import LOWPASS_VOXELS, inverse_covariances, opacity_field
from station.export.splat_model import SplatModel
from station.ngs.conventions import ALPHA_MAX, ALPHA_MIN


def dense_opacity(model: SplatModel, origin: np.ndarray, voxel: float, shape: tuple[int, int, int]) -> np.ndarray:
    """1 - prod(1 - alpha_i) with every Gaussian evaluated at every voxel centre, skip rule included."""
    axes = [origin[d] + voxel * np.arange(shape[d]) for d in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)                      # [X, Y, Z, 3]
    opacity = model.opacity().astype(np.float64)
    scales = np.sqrt(np.exp(2.0 * model.scales_log.astype(np.float64)) + (LOWPASS_VOXELS * voxel) ** 2)
    inv_cov = inverse_covariances(scales, model.quats.astype(np.float64))
    log_t = np.zeros(shape)
    for mean, inverse, o in zip(model.means.astype(np.float64), inv_cov, opacity):
        offset = centres - mean
        alpha = np.minimum(o * np.exp(-0.5 * np.einsum("...i,ij,...j->...", offset, inverse, offset)), ALPHA_MAX)
        log_t += np.where(alpha >= ALPHA_MIN, np.log1p(-np.where(alpha >= ALPHA_MIN, alpha, 0.0)), 0.0)
    return 1.0 - np.exp(log_t)


def test_the_field_equals_a_dense_evaluation_for_discs_needles_and_blobs():
    """The kernel visits only each Gaussian's alpha >= 1/255 ellipsoid; no voxel outside may be dropped."""
    rng = np.random.default_rng(7)
    n, voxel, shape = 60, 0.004, (26, 22, 24)
    origin = np.array([-0.05, -0.04, 0.0])
    scales = np.exp(rng.normal(np.log(0.006), 0.4, (n, 3)))
    scales[0::3, 2] = 1e-5       # flat discs, as on a trained surface
    scales[1::3, :2] = 2e-5      # needles
    quats = rng.normal(size=(n, 4))
    opacity = rng.uniform(0.0, 1.0, n)
    opacity[::5] = 1.5 / 255.0   # barely above the skip threshold
    opacity[::7] = 1.0 - 1e-9    # saturated
    means = origin + rng.uniform(0, 1, (n, 3)) * voxel * np.array(shape)
    model = SplatModel(means, np.log(scales), quats, np.log(opacity / (1 - opacity)), np.zeros((n, 3)),
                       np.zeros((n, 0, 3)))
    field = opacity_field(model, origin, voxel, shape)
    expected = dense_opacity(model, origin, voxel, shape)
    assert (expected > 0.5).mean() > 0.005 and (expected == 0).mean() > 0.2
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-12)


def test_where_the_transmittance_underflows_the_field_is_exactly_one_and_finite_everywhere():
    """Two thousand saturated Gaussians on one point: prod(1 - 0.99) leaves the float range there."""
    n, voxel, shape = 2_000, 0.004, (9, 9, 9)
    origin = np.full(3, -0.016)
    model = SplatModel(np.zeros((n, 3)), np.full((n, 3), np.log(0.004)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
                       np.full(n, 20.0), np.zeros((n, 3)), np.zeros((n, 0, 3)))
    field = opacity_field(model, origin, voxel, shape)
    assert np.isfinite(field).all() and field[4, 4, 4] == 1.0
    assert 0.99 < field[4, 4, 1] < 1.0 and field[0, 0, 0] == 0.0  # three voxels out; a corner, past 1/255
    np.testing.assert_allclose(field, dense_opacity(model, origin, voxel, shape), rtol=0, atol=1e-12)
