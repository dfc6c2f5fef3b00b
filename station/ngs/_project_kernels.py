"""numba kernels for EWA projection fused with SH colour, forward and hand-derived backward.

As small torch ops these dominated a CPU training step once compositing was fast, so each Gaussian is
handled in one pass here. Conventions match `raster_reference.project` and `eval_sh` exactly. The
backward writes per-(camera, Gaussian) pose partials and sums them in a fixed order: deterministic.

Laid out to compile fast on a fresh install: numba's IR-level `inline="always"` types a helper afresh at every
call site, and the parfor passes walk all that is inlined into a prange body, twice. So each prange body only
calls chunk functions, and helpers are `forceinline` (typed once, inlined by LLVM). Chunk functions and helpers
run without NRT (`_nrt=False`; none allocates): with it, every array argument of a call costs an atomic
reference-count pair per call.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from station.ngs._parallel import PRANGE_ONLY, NoAlias
from station.ngs.conventions import EPS2D, SH_C0, SH_C1, SH_C2, SH_C3

C20, C21, C22, C23, C24 = SH_C2
C30, C31, C32, C33, C34, C35, C36 = SH_C3


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _sh_basis(x, y, z, out):
    """Real SH basis up to degree 3 (gsplat/3DGS signs) at unit direction (x, y, z) into out[16]."""
    xx, yy, zz = x * x, y * y, z * z
    out[0] = SH_C0
    out[1] = -SH_C1 * y
    out[2] = SH_C1 * z
    out[3] = -SH_C1 * x
    out[4] = C20 * x * y
    out[5] = C21 * y * z
    out[6] = C22 * (2 * zz - xx - yy)
    out[7] = C23 * x * z
    out[8] = C24 * (xx - yy)
    out[9] = C30 * y * (3 * xx - yy)
    out[10] = C31 * x * y * z
    out[11] = C32 * y * (4 * zz - xx - yy)
    out[12] = C33 * z * (2 * zz - 3 * xx - 3 * yy)
    out[13] = C34 * x * (4 * zz - xx - yy)
    out[14] = C35 * z * (xx - yy)
    out[15] = C36 * x * (xx - 3 * yy)


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _sh_basis_grad(x, y, z, gx, gy, gz):
    """d basis_k / d(x, y, z) for k < 16 into gx, gy, gz [16]."""
    xx, yy, zz = x * x, y * y, z * z
    for k in range(16):
        gx[k] = 0.0
        gy[k] = 0.0
        gz[k] = 0.0
    gy[1] = -SH_C1
    gz[2] = SH_C1
    gx[3] = -SH_C1
    gx[4], gy[4] = C20 * y, C20 * x
    gy[5], gz[5] = C21 * z, C21 * y
    gx[6], gy[6], gz[6] = -2 * C22 * x, -2 * C22 * y, 4 * C22 * z
    gx[7], gz[7] = C23 * z, C23 * x
    gx[8], gy[8] = 2 * C24 * x, -2 * C24 * y
    gx[9], gy[9] = 6 * C30 * x * y, C30 * (3 * xx - 3 * yy)
    gx[10], gy[10], gz[10] = C31 * y * z, C31 * x * z, C31 * x * y
    gx[11], gy[11], gz[11] = -2 * C32 * x * y, C32 * (4 * zz - xx - 3 * yy), 8 * C32 * y * z
    gx[12], gy[12], gz[12] = -6 * C33 * x * z, -6 * C33 * y * z, C33 * (6 * zz - 3 * xx - 3 * yy)
    gx[13], gy[13], gz[13] = C34 * (4 * zz - 3 * xx - yy), -2 * C34 * x * y, 8 * C34 * x * z
    gx[14], gy[14], gz[14] = 2 * C35 * x * z, -2 * C35 * y * z, C35 * (xx - yy)
    gx[15], gy[15] = C36 * (3 * xx - 3 * yy), -6 * C36 * x * y


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _unit_rotation(q0, q1, q2, q3):
    """Norm, unit wxyz and row-major rotation [9] of an unnormalised wxyz quaternion. Scalars and tuples, not
    arrays: the forward's loop over Gaussians vectorises only without scratch arrays."""
    nrm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    w, x, y, z = q0 / nrm, q1 / nrm, q2 / nrm, q3 / nrm
    rot = (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
           2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
           2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return nrm, w, x, y, z, rot


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _times_transpose(a, b):
    """A B^T of two row-major 3 x 3 tuples [9]."""
    return (a[0] * b[0] + a[1] * b[1] + a[2] * b[2], a[0] * b[3] + a[1] * b[4] + a[2] * b[5],
            a[0] * b[6] + a[1] * b[7] + a[2] * b[8], a[3] * b[0] + a[4] * b[1] + a[5] * b[2],
            a[3] * b[3] + a[4] * b[4] + a[5] * b[5], a[3] * b[6] + a[4] * b[7] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[1] + a[8] * b[2], a[6] * b[3] + a[7] * b[4] + a[8] * b[5],
            a[6] * b[6] + a[7] * b[7] + a[8] * b[8])


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _covariances(rot, sx, sy, sz, rw):
    """World covariance R S S R^T and camera-frame covariance Rw cov Rw^T, row-major [9] each, from a Gaussian's
    rotation `rot` [9] and scales and the camera's rotation `rw` [9]."""
    m = (rot[0] * sx, rot[1] * sy, rot[2] * sz, rot[3] * sx, rot[4] * sy, rot[5] * sz, rot[6] * sx, rot[7] * sy,
         rot[8] * sz)
    cov = _times_transpose(m, m)
    rw_cov = _times_transpose(rw, cov)  # cov is symmetric: Rw cov^T is Rw cov
    return cov, _times_transpose(rw_cov, rw)


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _quat_rot(quats, g, R):
    """Unit rotation from Gaussian g's unnormalised wxyz quaternion into R [3, 3]; returns norm and unit quaternion."""
    nrm, w, x, y, z, rot = _unit_rotation(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])
    R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2] = rot
    return nrm, w, x, y, z


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _mm(A, B, out):
    """out = A @ B for A [r, 3], B [3, 3] (numba's @ calls BLAS and allocates: far too slow per Gaussian). Fixed
    sizes unroll; shapes as loop bounds make LLVM build vector loops of gathers, slower to run and to compile."""
    for i in range(A.shape[0]):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _camera_cov(quats, scales, g, Rw, cov, covc):
    """`_covariances` of Gaussian g into cov and covc [3, 3]."""
    rot = _unit_rotation(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])[5]
    rw = (Rw[0, 0], Rw[0, 1], Rw[0, 2], Rw[1, 0], Rw[1, 1], Rw[1, 2], Rw[2, 0], Rw[2, 1], Rw[2, 2])
    world, camera = _covariances(rot, scales[g, 0], scales[g, 1], scales[g, 2], rw)
    cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 0], cov[1, 1], cov[1, 2], cov[2, 0], cov[2, 1], cov[2, 2] = world
    covc[0, 0], covc[0, 1], covc[0, 2], covc[1, 0], covc[1, 1], covc[1, 2], covc[2, 0], covc[2, 1], covc[2, 2] = camera


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _jacobian(x, y, z, fx, fy, cx, cy, width, height):
    """EWA Jacobian entries (J00, J02, J11, J12) with gsplat's 1.3x frustum clamp, and the clamp flags."""
    lxp = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lxn = cx / fx + 0.3 * (0.5 * width / fx)
    lyp = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lyn = cy / fy + 0.3 * (0.5 * height / fy)
    rx, ry = x / z, y / z
    free_x = -lxn <= rx <= lxp
    free_y = -lyn <= ry <= lyp
    rx = min(max(rx, -lxn), lxp)
    ry = min(max(ry, -lyn), lyp)
    return fx / z, -fx * rx / z, fy / z, -fy * ry / z, free_x, free_y, rx, ry


CHUNK = 64


@njit(cache=True, _nrt=False, error_model="numpy", fastmath=True, pipeline_class=NoAlias)
def _project_chunk(c, start, means, quats, scales, viewmats, Ks, width, height, near, far, means2d, conics, depths,
                   radii, Rw, u_all, v_all, con_a, con_b, con_c):
    """Project Gaussians start .. start + CHUNK - 1 (fewer at the end) into camera c, writing every output slot.

    The geometry is one loop of straight-line code, which LLVM vectorises across Gaussians: no scratch arrays, no
    branches (selects), and five [N] arrays for means2d and conics, whose [C, N, k] rows it would have to scatter
    into (and rows of one [5, N] array might overlap, for all LLVM knows); they are copied over after. A Gaussian
    on the camera plane (z = 0) gets zeros."""
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    rw = (Rw[0, 0], Rw[0, 1], Rw[0, 2], Rw[1, 0], Rw[1, 1], Rw[1, 2], Rw[2, 0], Rw[2, 1], Rw[2, 2])
    tx, ty, tz = viewmats[c, 0, 3], viewmats[c, 1, 3], viewmats[c, 2, 3]
    stop = min(means.shape[0], start + CHUNK)
    for g in range(start, stop):
        px, py, pz = means[g, 0], means[g, 1], means[g, 2]
        x = rw[0] * px + rw[1] * py + rw[2] * pz + tx
        y = rw[3] * px + rw[4] * py + rw[5] * pz + ty
        z = rw[6] * px + rw[7] * py + rw[8] * pz + tz
        depths[c, g] = z
        front = z != 0.0
        zs = z if front else 1.0  # anything finite: a Gaussian on the camera plane gets zeros below
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        rot = _unit_rotation(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])[5]
        k = _covariances(rot, scales[g, 0], scales[g, 1], scales[g, 2], rw)[1]
        j00, j02, j11, j12, _, _, _, _ = _jacobian(x, y, zs, fx, fy, cx, cy, width, height)
        a = j00 * j00 * k[0] + 2 * j00 * j02 * k[2] + j02 * j02 * k[8] + EPS2D
        b = j00 * j11 * k[1] + j00 * j12 * k[2] + j02 * j11 * k[7] + j02 * j12 * k[8]
        cc = j11 * j11 * k[4] + 2 * j11 * j12 * k[5] + j12 * j12 * k[8] + EPS2D
        det = a * cc - b * b
        inv_det = 1.0 / max(det, 1e-10)
        half = 0.5 * (a + cc)
        v1 = half + math.sqrt(max(half * half - det, 0.01))
        radius = np.ceil(3.0 * math.sqrt(max(v1, 0.0)))  # np.ceil: a float, where math.ceil converts to int
        visible = (det > 0) & (near < z) & (z < far)
        inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        u_all[g] = u if front else 0.0
        v_all[g] = v if front else 0.0
        con_a[g] = cc * inv_det if front else 0.0
        con_b[g] = -b * inv_det if front else 0.0
        con_c[g] = a * inv_det if front else 0.0
        radii[c, g] = np.int32(radius) if visible & inside & front else np.int32(0)
    for g in range(start, stop):
        means2d[c, g, 0], means2d[c, g, 1] = u_all[g], v_all[g]
        conics[c, g, 0], conics[c, g, 1], conics[c, g, 2] = con_a[g], con_b[g], con_c[g]


@njit(cache=True, _nrt=False, error_model="numpy", fastmath=True)
def _sh_chunk(c, start, means, coeffs, sh_degree, campos, depths, colors, basis):
    """SH colour of Gaussians start .. start + CHUNK - 1 (fewer at the end) seen from camera c, a Gaussian at a time;
    those on its plane (z = 0) keep their zeros."""
    for g in range(start, min(means.shape[0], start + CHUNK)):
        if depths[c, g] == 0.0:
            continue
        dx, dy, dz = means[g, 0] - campos[c, 0], means[g, 1] - campos[c, 1], means[g, 2] - campos[c, 2]
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        _sh_basis(dx / nd, dy / nd, dz / nd, basis)
        red, green, blue = 0.0, 0.0, 0.0  # coefficient by coefficient, the channels side by side: contiguous loads
        for k in range((sh_degree + 1) ** 2):
            red += basis[k] * coeffs[g, k, 0]
            green += basis[k] * coeffs[g, k, 1]
            blue += basis[k] * coeffs[g, k, 2]
        colors[c, g, 0] = max(red + 0.5, 0.0)
        colors[c, g, 1] = max(green + 0.5, 0.0)
        colors[c, g, 2] = max(blue + 0.5, 0.0)


@njit(parallel=PRANGE_ONLY, cache=True, error_model="numpy", fastmath=True)
def project_fwd(means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, near, far):
    """-> means2d [C,N,2], conics [C,N,3], depths [C,N], radii [C,N] int32, colors [C,N,3] (SH; zeros if deg < 0)."""
    c_n, n = viewmats.shape[0], means.shape[0]
    dt = means.dtype
    means2d = np.zeros((c_n, n, 2), dt)
    conics = np.zeros((c_n, n, 3), dt)
    depths = np.zeros((c_n, n), dt)
    radii = np.zeros((c_n, n), np.int32)
    colors = np.zeros((c_n, n, 3), dt)
    planar = (np.empty(n, dt), np.empty(n, dt), np.empty(n, dt), np.empty(n, dt), np.empty(n, dt))
    for c in range(c_n):
        Rw = viewmats[c, :3, :3].astype(np.float64)
        for chunk in prange((n + CHUNK - 1) // CHUNK):
            _project_chunk(c, chunk * CHUNK, means, quats, scales, viewmats, Ks, width, height, near, far, means2d,
                           conics, depths, radii, Rw, *planar)
            if sh_degree >= 0:
                _sh_chunk(c, chunk * CHUNK, means, coeffs, sh_degree, campos, depths, colors, np.empty(16))
    return means2d, conics, depths, radii, colors


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _project_one_bwd(c, g, means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, colors,
                     upstream, outs, Rw, scratch, want_pose):
    """Backward of `_project_one` for (c, g): adds into outs = (g_means, g_coeffs, g_cov (world covariance),
    pose_part; written only if want_pose). upstream = (g_means2d, g_conics, g_depths, g_colors). scratch holds
    [3, 3] buffers but for J, jc [2, 3] and the SH buffers [16]."""
    g_means2d, g_conics, g_depths, g_colors = upstream
    g_means, g_coeffs, g_cov, pose_part = outs
    _, _, cov, covc, t33, g_covc, gR, J, jc, basis, bx, by, bz = scratch
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    x = Rw[0, 0] * means[g, 0] + Rw[0, 1] * means[g, 1] + Rw[0, 2] * means[g, 2] + viewmats[c, 0, 3]
    y = Rw[1, 0] * means[g, 0] + Rw[1, 1] * means[g, 1] + Rw[1, 2] * means[g, 2] + viewmats[c, 1, 3]
    z = Rw[2, 0] * means[g, 0] + Rw[2, 1] * means[g, 1] + Rw[2, 2] * means[g, 2] + viewmats[c, 2, 3]
    _camera_cov(quats, scales, g, Rw, cov, covc)
    j00, j02, j11, j12, free_x, free_y, rx, ry = _jacobian(x, y, z, fx, fy, cx, cy, width, height)
    J[0, 0], J[0, 1], J[0, 2], J[1, 0], J[1, 1], J[1, 2] = j00, 0.0, j02, 0.0, j11, j12
    _mm(J, covc, jc)                                       # J covc [2, 3]
    a = jc[0, 0] * J[0, 0] + jc[0, 2] * J[0, 2] + EPS2D
    b = jc[0, 1] * J[1, 1] + jc[0, 2] * J[1, 2]
    cc = jc[1, 1] * J[1, 1] + jc[1, 2] * J[1, 2] + EPS2D
    det = max(a * cc - b * b, 1e-10)
    qa, qb, qc = cc / det, -b / det, a / det
    ga, gb, gc = g_conics[c, g, 0], 0.5 * g_conics[c, g, 1], g_conics[c, g, 2]
    # d loss / d cov2d = -Q G Q (Q = conic matrix, G = its symmetric gradient)
    g2_00 = -(qa * (qa * ga + qb * gb) + qb * (qa * gb + qb * gc))
    g2_01 = -(qa * (qb * ga + qc * gb) + qb * (qb * gb + qc * gc))
    g2_11 = -(qb * (qb * ga + qc * gb) + qc * (qb * gb + qc * gc))
    for i in range(3):
        for j in range(3):
            g_covc[i, j] = (J[0, i] * (g2_00 * J[0, j] + g2_01 * J[1, j])
                            + J[1, i] * (g2_01 * J[0, j] + g2_11 * J[1, j]))
    # gJ = 2 g2 (J covc)
    gj00 = 2 * (g2_00 * jc[0, 0] + g2_01 * jc[1, 0])
    gj02 = 2 * (g2_00 * jc[0, 2] + g2_01 * jc[1, 2])
    gj11 = 2 * (g2_01 * jc[0, 1] + g2_11 * jc[1, 1])
    gj12 = 2 * (g2_01 * jc[0, 2] + g2_11 * jc[1, 2])
    gu, gv = g_means2d[c, g, 0], g_means2d[c, g, 1]
    z2 = z * z
    gx = fx / z * gu
    gy = fy / z * gv
    gz = -fx * x / z2 * gu - fy * y / z2 * gv + g_depths[c, g]
    gz += -fx / z2 * gj00 - fy / z2 * gj11 + fx * rx / z2 * gj02 + fy * ry / z2 * gj12
    if free_x:
        gx += -fx / z2 * gj02
        gz += fx * x / (z2 * z) * gj02
    if free_y:
        gy += -fy / z2 * gj12
        gz += fy * y / (z2 * z) * gj12
    # covc = Rw cov Rw^T: g_cov += Rw^T g_covc Rw ; gR = 2 g_covc Rw cov
    for i in range(3):
        for j in range(3):
            t33[i, j] = Rw[0, i] * g_covc[0, j] + Rw[1, i] * g_covc[1, j] + Rw[2, i] * g_covc[2, j]
    for i in range(3):
        for j in range(3):
            g_cov[i, j] += t33[i, 0] * Rw[0, j] + t33[i, 1] * Rw[1, j] + t33[i, 2] * Rw[2, j]
    g_mc = (gx, gy, gz)
    for i in range(3):
        for j in range(3):
            g_means[g, j] += Rw[i, j] * g_mc[i]
    if want_pose:
        _mm(g_covc, Rw, t33)
        _mm(t33, cov, gR)
        for i in range(3):
            for j in range(3):
                pose_part[c, g, 3 * i + j] = 2 * gR[i, j] + g_mc[i] * means[g, j]
            pose_part[c, g, 9 + i] = g_mc[i]
    if sh_degree >= 0:
        d0, d1, d2 = means[g, 0] - campos[c, 0], means[g, 1] - campos[c, 1], means[g, 2] - campos[c, 2]
        nd = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        u0, u1, u2 = d0 / nd, d1 / nd, d2 / nd
        _sh_basis(u0, u1, u2, basis)
        _sh_basis_grad(u0, u1, u2, bx, by, bz)
        gd0 = 0.0
        gd1 = 0.0
        gd2 = 0.0
        g_r = g_colors[c, g, 0] if colors[c, g, 0] > 0.0 else 0.0  # no gradient where the colour was clamped to 0
        g_g = g_colors[c, g, 1] if colors[c, g, 1] > 0.0 else 0.0
        g_b = g_colors[c, g, 2] if colors[c, g, 2] > 0.0 else 0.0
        for k in range((sh_degree + 1) ** 2):
            g_coeffs[g, k, 0] += basis[k] * g_r
            g_coeffs[g, k, 1] += basis[k] * g_g
            g_coeffs[g, k, 2] += basis[k] * g_b
            g_basis = coeffs[g, k, 0] * g_r + coeffs[g, k, 1] * g_g + coeffs[g, k, 2] * g_b
            gd0 += bx[k] * g_basis
            gd1 += by[k] * g_basis
            gd2 += bz[k] * g_basis
        dot = u0 * gd0 + u1 * gd1 + u2 * gd2
        gm = ((gd0 - u0 * dot) / nd, (gd1 - u1 * dot) / nd, (gd2 - u2 * dot) / nd)
        for i in range(3):
            g_means[g, i] += gm[i]
            if want_pose:
                pose_part[c, g, 12 + i] = -gm[i]


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _cov_to_params(g, quats, scales, g_cov, g_quats, g_scales, R, M, gM):
    """Chain d loss / d world covariance into the (unnormalised) quaternion and the scales of Gaussian g."""
    nrm, w, x, y, z = _quat_rot(quats, g, R)
    for i in range(3):
        for j in range(3):
            M[i, j] = R[i, j] * scales[g, j]
    for i in range(3):
        for j in range(3):
            gM[i, j] = ((g_cov[i, 0] + g_cov[0, i]) * M[0, j] + (g_cov[i, 1] + g_cov[1, i]) * M[1, j]
                        + (g_cov[i, 2] + g_cov[2, i]) * M[2, j])
    for j in range(3):
        g_scales[g, j] = gM[0, j] * R[0, j] + gM[1, j] * R[1, j] + gM[2, j] * R[2, j]
        for i in range(3):
            gM[i, j] *= scales[g, j]
    G = gM
    gw = 2 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
    gx = 2 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
              + w * G[2, 1] - 2 * x * G[2, 2])
    gy = 2 * (-2 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
              + z * G[2, 1] - 2 * y * G[2, 2])
    gz = 2 * (-2 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2 * z * G[1, 1] + y * G[1, 2]
              + x * G[2, 0] + y * G[2, 1])
    dot = w * gw + x * gx + y * gy + z * gz
    g_quats[g, 0] = (gw - w * dot) / nrm
    g_quats[g, 1] = (gx - x * dot) / nrm
    g_quats[g, 2] = (gy - y * dot) / nrm
    g_quats[g, 3] = (gz - z * dot) / nrm


@njit(cache=True, forceinline=True, _nrt=False)
def _has_upstream(c, g, g_means2d, g_conics, g_depths, g_colors):
    """Whether Gaussian g has a non-zero upstream gradient in camera c. One hidden in that view (the back of the
    stone, most of the NGS noise) has none, and its backward would only add zeros: about half of them in an NGS
    training step."""
    if g_depths[c, g] != 0.0:
        return True
    for i in range(2):
        if g_means2d[c, g, i] != 0.0:
            return True
    for i in range(3):
        if g_conics[c, g, i] != 0.0:
            return True
    for i in range(g_colors.shape[2]):
        if g_colors[c, g, i] != 0.0:
            return True
    return False


@njit(cache=True, _nrt=False, error_model="numpy", fastmath=True, pipeline_class=NoAlias)
def _project_bwd_chunk(start, means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, radii,
                       colors, Rws, upstream, want_pose, outs, g_quats, g_scales, Rw, scratch):
    """The backward of Gaussians start .. start + CHUNK - 1 (fewer at the end) over every camera; arguments as
    `_project_one_bwd`'s, Rws [C, 3, 3] the cameras' rotations and Rw [3, 3] scratch."""
    g_means2d, g_conics, g_depths, g_colors = upstream
    g_means, g_coeffs, g_cov = outs[0], outs[1], outs[2]
    s0, s1, gR = scratch[0], scratch[1], scratch[6]
    for g in range(start, min(means.shape[0], start + CHUNK)):
        for i in range(3):
            g_means[g, i] = 0.0
            for j in range(3):
                g_cov[i, j] = 0.0
        for k in range(g_coeffs.shape[1]):
            for i in range(3):
                g_coeffs[g, k, i] = 0.0
        seen = False
        for c in range(viewmats.shape[0]):
            if radii[c, g] > 0 and _has_upstream(c, g, g_means2d, g_conics, g_depths, g_colors):
                seen = True
                for i in range(3):
                    for j in range(3):
                        Rw[i, j] = Rws[c, i, j]
                _project_one_bwd(c, g, means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width,
                                 height, colors, upstream, outs, Rw, scratch, want_pose)
        if seen:
            _cov_to_params(g, quats, scales, g_cov, g_quats, g_scales, s0, s1, gR)
        else:
            for i in range(4):
                g_quats[g, i] = 0.0
            for i in range(3):
                g_scales[g, i] = 0.0


@njit(parallel=PRANGE_ONLY, cache=True, error_model="numpy", fastmath=True)
def project_bwd(means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, radii, colors,
                g_means2d, g_conics, g_depths, g_colors, want_pose=True):
    """-> g_means [N,3], g_quats [N,4], g_scales [N,3], g_coeffs [N,K,3], g_viewmats [C,4,4], g_campos [C,3]
    (the last two zero unless want_pose: training poses are constants, so their partials are skipped)."""
    c_n, n = viewmats.shape[0], means.shape[0]
    dt = means.dtype
    g_means = np.empty((n, 3), dt)  # each Gaussian's rows are zeroed in its chunk: np.zeros is a serial memset
    g_quats = np.empty((n, 4), dt)
    g_scales = np.empty((n, 3), dt)
    g_coeffs = np.empty(coeffs.shape, dt)
    pose_part = np.zeros((c_n, n if want_pose else 0, 15))  # per (camera, Gaussian): d Rw (9), d t (3), d campos (3)
    Rws = np.empty((c_n, 3, 3))
    # loops here and below, not Rws[c] = viewmats[c, :3, :3] and pose_part.sum(axis=1): those compile error paths
    # and string code for seconds
    for c in range(c_n):
        for i in range(3):
            for j in range(3):
                Rws[c, i, j] = viewmats[c, i, j]
    for chunk in prange((n + CHUNK - 1) // CHUNK):
        scratch = (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
                   np.empty((3, 3)), np.empty((3, 3)), np.empty((2, 3)), np.empty((2, 3)), np.empty(16), np.empty(16),
                   np.empty(16), np.empty(16))
        _project_bwd_chunk(chunk * CHUNK, means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height,
                           radii, colors, Rws, (g_means2d, g_conics, g_depths, g_colors), want_pose,
                           (g_means, g_coeffs, np.empty((3, 3)), pose_part), g_quats, g_scales, np.empty((3, 3)),
                           scratch)
    pose = np.zeros((c_n, 15))                             # [C, 15], summed in a fixed order
    for c in range(c_n):
        for g in range(pose_part.shape[1]):
            for k in range(15):
                pose[c, k] += pose_part[c, g, k]
    g_viewmats = np.zeros((c_n, 4, 4), dt)
    g_campos = np.zeros((c_n, 3), dt)
    for c in range(c_n):
        for i in range(3):
            for j in range(3):
                g_viewmats[c, i, j] = pose[c, 3 * i + j]
            g_viewmats[c, i, 3] = pose[c, 9 + i]
            g_campos[c, i] = pose[c, 12 + i]
    return g_means, g_quats, g_scales, g_coeffs, g_viewmats, g_campos
