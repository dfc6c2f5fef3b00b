"""numba kernels of the training SSIM: the five local moments and the SSIM map in one pass, and its gradient.

Same definition as `losses.ssim` (the plain-torch reference): an 11-tap Gaussian window (sigma 1.5),
separable, over 'valid' windows, mean over channels and windows. The forward keeps, per window, the
derivatives of SSIM with respect to the three moments the render enters (mean, mean square, mean product);
the backward spreads them back over each window's pixels with the same taps (the transpose of the
filter), so no image-sized intermediate goes through autograd. Images are [C, H, W], rows contiguous.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from station.ngs._parallel import PRANGE_ONLY

C1 = 0.01**2
C2 = 0.03**2


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def ssim_fwd(x, y, taps):
    """-> (sum of the SSIM map, d SSIM / d mean_x, d SSIM / d mean(x^2), d SSIM / d mean(xy)), maps [C, H', W']."""
    n_ch, h, w = x.shape
    k = taps.shape[0]
    ho, wo = h - k + 1, w - k + 1
    dt = x.dtype
    rows = np.empty((5, n_ch, h, wo), dt)  # horizontal pass: x, y, x^2, y^2, xy
    for job in prange(n_ch * h):
        c, i = job // h, job % h
        for m in range(5):
            for j in range(wo):
                rows[m, c, i, j] = 0.0
        for b in range(k):
            t = taps[b]
            for j in range(wo):
                xv = x[c, i, j + b]
                yv = y[c, i, j + b]
                rows[0, c, i, j] += t * xv
                rows[1, c, i, j] += t * yv
                rows[2, c, i, j] += t * xv * xv
                rows[3, c, i, j] += t * yv * yv
                rows[4, c, i, j] += t * xv * yv
    d_mu = np.empty((n_ch, ho, wo), dt)
    d_xx = np.empty((n_ch, ho, wo), dt)
    d_xy = np.empty((n_ch, ho, wo), dt)
    row_sums = np.zeros(n_ch * ho, np.float64)
    for job in prange(n_ch * ho):
        c, i = job // ho, job % ho
        mom = np.zeros((5, wo), dt)
        for a in range(k):
            t = taps[a]
            for m in range(5):
                for j in range(wo):
                    mom[m, j] += t * rows[m, c, i + a, j]
        total = 0.0
        for j in range(wo):
            mx, my = mom[0, j], mom[1, j]
            sxx = mom[2, j] - mx * mx
            syy = mom[3, j] - my * my
            sxy = mom[4, j] - mx * my
            a1 = 2.0 * mx * my + C1
            a2 = 2.0 * sxy + C2
            b1 = mx * mx + my * my + C1
            b2 = sxx + syy + C2
            inv = 1.0 / (b1 * b2)
            s = a1 * a2 * inv
            total += s
            d_mu[c, i, j] = 2.0 * my * (a2 - a1) * inv - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2)
            d_xx[c, i, j] = -s / b2
            d_xy[c, i, j] = 2.0 * a1 * inv
        row_sums[job] = total
    return row_sums.sum(), d_mu, d_xx, d_xy


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def ssim_bwd(scale, x, y, taps, d_mu, d_xx, d_xy):
    """d (scale * sum of the SSIM map) / d x -> [C, H, W]: each window's derivatives spread back over its pixels."""
    n_ch, h, w = x.shape
    k = taps.shape[0]
    ho, wo = d_mu.shape[1], d_mu.shape[2]
    dt = x.dtype
    cols = np.empty((3, n_ch, h, wo), dt)  # transpose of the vertical pass
    for job in prange(n_ch * h):
        c, i = job // h, job % h
        for m in range(3):
            for j in range(wo):
                cols[m, c, i, j] = 0.0
        for a in range(max(0, i - ho + 1), min(k, i + 1)):
            t = taps[a]
            for j in range(wo):
                cols[0, c, i, j] += t * d_mu[c, i - a, j]
                cols[1, c, i, j] += t * d_xx[c, i - a, j]
                cols[2, c, i, j] += t * d_xy[c, i - a, j]
    grad = np.empty((n_ch, h, w), dt)
    for job in prange(n_ch * h):
        c, i = job // h, job % h
        acc = np.zeros((3, w), dt)
        for b in range(k):
            t = taps[b]
            for m in range(3):
                for j in range(wo):
                    acc[m, j + b] += t * cols[m, c, i, j]
        for q in range(w):
            grad[c, i, q] = scale * (acc[0, q] + 2.0 * x[c, i, q] * acc[1, q] + y[c, i, q] * acc[2, q])
    return grad
