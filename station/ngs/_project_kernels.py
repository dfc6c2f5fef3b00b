"""numba kernels for EWA projection fused with SH colour, forward and hand-derived backward.

As small torch ops these dominated a CPU training step once compositing was fast, so each Gaussian is
handled in one pass here. Conventions match `raster_reference.project` and `eval_sh` exactly. The
backward sums pose partials per camera and chunk of Gaussians, then over chunks in a fixed order: deterministic
at any thread count.

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
def _sh_basis_grad(x, y, z):
    """d basis_k / d(x, y, z) for k < 16: three tuples [16], which stay in registers."""
    xx, yy, zz = x * x, y * y, z * z
    gx = (0.0, 0.0, 0.0, -SH_C1, C20 * y, 0.0, -2 * C22 * x, C23 * z, 2 * C24 * x, 6 * C30 * x * y, C31 * y * z,
          -2 * C32 * x * y, -6 * C33 * x * z, C34 * (4 * zz - 3 * xx - yy), 2 * C35 * x * z, C36 * (3 * xx - 3 * yy))
    gy = (0.0, -SH_C1, 0.0, 0.0, C20 * x, C21 * z, -2 * C22 * y, 0.0, -2 * C24 * y, C30 * (3 * xx - 3 * yy),
          C31 * x * z, C32 * (4 * zz - xx - 3 * yy), -6 * C33 * y * z, -2 * C34 * x * y, -2 * C35 * y * z,
          -6 * C36 * x * y)
    gz = (0.0, 0.0, SH_C1, 0.0, 0.0, C21 * y, 4 * C22 * z, C23 * x, 0.0, 0.0, C31 * x * y, 8 * C32 * y * z,
          C33 * (6 * zz - 3 * xx - 3 * yy), 8 * C34 * x * z, C35 * (xx - yy), 0.0)
    return gx, gy, gz


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


@njit(cache=True)
def _rotations(viewmats):
    """The cameras' world-to-camera rotations [C, 3, 3] in float64. An array, not float() of each entry where it is
    used: LLVM then knows those are widened float32 and rounds the products that use them differently."""
    rws = np.empty((viewmats.shape[0], 3, 3))
    for c in range(viewmats.shape[0]):  # loops, not rws[c] = viewmats[c, :3, :3]: that compiles error paths for seconds
        for i in range(3):
            for j in range(3):
                rws[c, i, j] = viewmats[c, i, j]
    return rws


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _camera_rotation(rws, c):
    """Camera c's rotation from `_rotations` as a row-major tuple [9]."""
    return (rws[c, 0, 0], rws[c, 0, 1], rws[c, 0, 2], rws[c, 1, 0], rws[c, 1, 1], rws[c, 1, 2], rws[c, 2, 0],
            rws[c, 2, 1], rws[c, 2, 2])


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _to_camera(rw, viewmats, c, px, py, pz):
    """World point (px, py, pz) in camera c's frame, rw its `_camera_rotation`."""
    return (rw[0] * px + rw[1] * py + rw[2] * pz + viewmats[c, 0, 3],
            rw[3] * px + rw[4] * py + rw[5] * pz + viewmats[c, 1, 3],
            rw[6] * px + rw[7] * py + rw[8] * pz + viewmats[c, 2, 3])


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _cov2d(j00, j02, j11, j12, k):
    """The 2D covariance J k J^T (a, b, c; EPS2D added on the diagonal) of camera-frame covariance k [9], J the
    `_jacobian` [[j00, 0, j02], [0, j11, j12]]: the forward's, and the backward's recomputation of it."""
    a = j00 * j00 * k[0] + 2 * j00 * j02 * k[2] + j02 * j02 * k[8] + EPS2D
    b = j00 * j11 * k[1] + j00 * j12 * k[2] + j02 * j11 * k[7] + j02 * j12 * k[8]
    cc = j11 * j11 * k[4] + 2 * j11 * j12 * k[5] + j12 * j12 * k[8] + EPS2D
    return a, b, cc


CHUNK = 64


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _at(flat, row, width, k):
    """Element k of row `row` of a flattened [rows, width] array. An [N, k] array's strides are runtime values to
    LLVM: it vectorised the projection's backward only behind a check that the row length is 1, so the vector code
    never ran, and the forward with gathers. A constant width and an unsigned index give it unit strides."""
    return flat[row * np.uint64(width) + np.uint64(k)]


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _put(flat, g, values):
    """Row g of a flattened [N, len(values)] array. A constant row length and an unsigned index let LLVM vectorise
    a loop of these stores; with an [N, k] array's runtime strides, rows might overlap for all it knows."""
    row = g * np.uint64(len(values))
    for k in range(len(values)):
        flat[row + np.uint64(k)] = values[k]


@njit(cache=True, _nrt=False, error_model="numpy", fastmath=True, pipeline_class=NoAlias)
def _project_chunk(c, start, means, quats, scales, viewmats, rws, Ks, width, height, near, far, means2d, conics,
                   depths, radii):
    """Project Gaussians start .. start + CHUNK - 1 (fewer at the end) into camera c, writing every output slot.

    The geometry is one loop of straight-line code, which LLVM vectorises across Gaussians: no scratch arrays and
    no branches (selects); means, quats and scales come flattened (`_at`), means2d and conics too (`_put`). A
    Gaussian on the camera plane (z = 0) gets zeros."""
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    rw = _camera_rotation(rws, c)
    stop = min(depths.shape[1], start + CHUNK)
    for g in range(np.uint64(start), np.uint64(stop)):
        x, y, z = _to_camera(rw, viewmats, c, _at(means, g, 3, 0), _at(means, g, 3, 1), _at(means, g, 3, 2))
        depths[c, g] = z
        front = z != 0.0
        zs = z if front else 1.0  # anything finite: a Gaussian on the camera plane gets zeros below
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        rot = _unit_rotation(_at(quats, g, 4, 0), _at(quats, g, 4, 1), _at(quats, g, 4, 2), _at(quats, g, 4, 3))[5]
        k = _covariances(rot, _at(scales, g, 3, 0), _at(scales, g, 3, 1), _at(scales, g, 3, 2), rw)[1]
        j00, j02, j11, j12, _, _, _, _ = _jacobian(x, y, zs, fx, fy, cx, cy, width, height)
        a, b, cc = _cov2d(j00, j02, j11, j12, k)
        det = a * cc - b * b
        inv_det = 1.0 / max(det, 1e-10)
        half = 0.5 * (a + cc)
        v1 = half + math.sqrt(max(half * half - det, 0.01))
        radius = np.ceil(3.0 * math.sqrt(max(v1, 0.0)))  # np.ceil: a float, where math.ceil converts to int
        visible = (det > 0) & (near < z) & (z < far)
        inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        cg = np.uint64(c) * np.uint64(depths.shape[1]) + g
        _put(means2d, cg, (u if front else 0.0, v if front else 0.0))
        inv_det = inv_det if front else 0.0
        _put(conics, cg, (cc * inv_det, -b * inv_det, a * inv_det))
        radii[c, g] = np.int32(radius) if visible & inside & front else np.int32(0)


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
    flat = (means2d.reshape(2 * c_n * n), conics.reshape(3 * c_n * n))  # views, for `_put`
    flat_in = (means.reshape(3 * n), quats.reshape(4 * n), scales.reshape(3 * n))  # and for `_at`
    rws = _rotations(viewmats)
    for c in range(c_n):
        for chunk in prange((n + CHUNK - 1) // CHUNK):
            _project_chunk(c, chunk * CHUNK, *flat_in, viewmats, rws, Ks, width, height, near, far, *flat, depths,
                           radii)
            if sh_degree >= 0:
                _sh_chunk(c, chunk * CHUNK, means, coeffs, sh_degree, campos, depths, colors, np.empty(16))
    return means2d, conics, depths, radii, colors


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _transposed(a):
    """A^T of a row-major 3 x 3 tuple [9]."""
    return a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _geometry_bwd(c, g, means, quats, scales, viewmats, Ks, width, height, radii, g_means2d, g_conics, g_depths, rw):
    """Backward of `_project_chunk`'s geometry for (c, g), in scalars and tuples so that a loop over Gaussians
    vectorises: -> d loss / d mean in world (3), d loss / d world covariance (row-major [9], symmetric), and the pose
    partials d Rw (9) and d t (3). A Gaussian camera c does not draw (radii 0) gets zeros: its upstream is taken as
    zero and its depth as 1, so nothing divides by zero. means, quats, scales, g_means2d and g_conics come
    flattened (`_at`), and g is unsigned."""
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    px, py, pz = _at(means, g, 3, 0), _at(means, g, 3, 1), _at(means, g, 3, 2)
    cg = np.uint64(c) * np.uint64(radii.shape[1]) + g
    x, y, z = _to_camera(rw, viewmats, c, px, py, pz)
    seen = radii[c, g] > 0
    z = z if seen else 1.0
    rot = _unit_rotation(_at(quats, g, 4, 0), _at(quats, g, 4, 1), _at(quats, g, 4, 2), _at(quats, g, 4, 3))[5]
    cov, k = _covariances(rot, _at(scales, g, 3, 0), _at(scales, g, 3, 1), _at(scales, g, 3, 2), rw)
    j00, j02, j11, j12, free_x, free_y, rx, ry = _jacobian(x, y, z, fx, fy, cx, cy, width, height)
    jc00, jc01, jc02 = j00 * k[0] + j02 * k[6], j00 * k[1] + j02 * k[7], j00 * k[2] + j02 * k[8]   # J covc [2, 3]
    jc10, jc11, jc12 = j11 * k[3] + j12 * k[6], j11 * k[4] + j12 * k[7], j11 * k[5] + j12 * k[8]
    a, b, cc = _cov2d(j00, j02, j11, j12, k)
    det = max(a * cc - b * b, 1e-10)
    qa, qb, qc = cc / det, -b / det, a / det
    ga = _at(g_conics, cg, 3, 0) if seen else 0.0
    gb = 0.5 * _at(g_conics, cg, 3, 1) if seen else 0.0
    gc = _at(g_conics, cg, 3, 2) if seen else 0.0
    # d loss / d cov2d = -Q G Q (Q = conic matrix, G = its symmetric gradient)
    g2_00 = -(qa * (qa * ga + qb * gb) + qb * (qa * gb + qb * gc))
    g2_01 = -(qa * (qb * ga + qc * gb) + qb * (qb * gb + qc * gc))
    g2_11 = -(qb * (qb * ga + qc * gb) + qc * (qb * gb + qc * gc))
    # d loss / d covc = J^T g2 J, J = [[j00, 0, j02], [0, j11, j12]]
    h00, h01 = g2_00 * j00, g2_01 * j00
    h10, h11 = g2_01 * j11, g2_11 * j11
    h20, h21 = g2_00 * j02 + g2_01 * j12, g2_01 * j02 + g2_11 * j12
    g_covc = (j00 * h00, j00 * h10, j00 * h20, j11 * h01, j11 * h11, j11 * h21,
              j02 * h00 + j12 * h01, j02 * h10 + j12 * h11, j02 * h20 + j12 * h21)
    gj00 = 2 * (g2_00 * jc00 + g2_01 * jc10)                # gJ = 2 g2 (J covc)
    gj02 = 2 * (g2_00 * jc02 + g2_01 * jc12)
    gj11 = 2 * (g2_01 * jc01 + g2_11 * jc11)
    gj12 = 2 * (g2_01 * jc02 + g2_11 * jc12)
    gu = _at(g_means2d, cg, 2, 0) if seen else 0.0
    gv = _at(g_means2d, cg, 2, 1) if seen else 0.0
    gd = g_depths[c, g] if seen else 0.0
    z2 = z * z
    gx = fx / z * gu + (-fx / z2 * gj02 if free_x else 0.0)
    gy = fy / z * gv + (-fy / z2 * gj12 if free_y else 0.0)
    gz = (-fx * x / z2 * gu - fy * y / z2 * gv + gd - fx / z2 * gj00 - fy / z2 * gj11 + fx * rx / z2 * gj02
          + fy * ry / z2 * gj12 + (fx * x / (z2 * z) * gj02 if free_x else 0.0)
          + (fy * y / (z2 * z) * gj12 if free_y else 0.0))
    rwt = _transposed(rw)
    g_cov = _times_transpose(_times_transpose(rwt, g_covc), rwt)     # covc = Rw cov Rw^T: Rw^T g_covc Rw
    g_mean = (rw[0] * gx + rw[3] * gy + rw[6] * gz, rw[1] * gx + rw[4] * gy + rw[7] * gz,
              rw[2] * gx + rw[5] * gy + rw[8] * gz)
    g_r = _times_transpose(_times_transpose(g_covc, rwt), cov)      # d Rw / 2 = g_covc Rw cov
    g_rw = (2 * g_r[0] + gx * px, 2 * g_r[1] + gx * py, 2 * g_r[2] + gx * pz,
            2 * g_r[3] + gy * px, 2 * g_r[4] + gy * py, 2 * g_r[5] + gy * pz,
            2 * g_r[6] + gz * px, 2 * g_r[7] + gz * py, 2 * g_r[8] + gz * pz)
    return g_mean, g_cov, g_rw, (gx, gy, gz)


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _cov_to_params(q0, q1, q2, q3, sx, sy, sz, s):
    """Chain d loss / d world covariance, its upper triangle s [6], into the unnormalised wxyz quaternion and the
    scales: -> (d quaternion [4], d scales [3])."""
    nrm, w, x, y, z, rot = _unit_rotation(q0, q1, q2, q3)
    m = (rot[0] * sx, rot[1] * sy, rot[2] * sz, rot[3] * sx, rot[4] * sy, rot[5] * sz, rot[6] * sx, rot[7] * sy,
         rot[8] * sz)                                         # cov = M M^T, M = R S
    sym = (2 * s[0], 2 * s[1], 2 * s[2], 2 * s[1], 2 * s[3], 2 * s[4], 2 * s[2], 2 * s[4], 2 * s[5])
    gm = _times_transpose(sym, _transposed(m))                # d M = (g + g^T) M
    g_scales = (gm[0] * rot[0] + gm[3] * rot[3] + gm[6] * rot[6], gm[1] * rot[1] + gm[4] * rot[4] + gm[7] * rot[7],
                gm[2] * rot[2] + gm[5] * rot[5] + gm[8] * rot[8])
    G = (gm[0] * sx, gm[1] * sy, gm[2] * sz, gm[3] * sx, gm[4] * sy, gm[5] * sz, gm[6] * sx, gm[7] * sy, gm[8] * sz)
    gw = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7])
    gx = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8])
    gy = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8])
    gz = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7])
    dot = w * gw + x * gx + y * gy + z * gz
    return ((gw - w * dot) / nrm, (gx - x * dot) / nrm, (gy - y * dot) / nrm, (gz - z * dot) / nrm), g_scales


@njit(cache=True, forceinline=True, _nrt=False, error_model="numpy", fastmath=True)
def _accumulate(g, g_mean, g_cov, mx, my, mz, s00, s01, s02, s11, s12, s22):
    """Add one camera's mean and world-covariance gradient of Gaussian g into the [N] sums."""
    mx[g] += g_mean[0]
    my[g] += g_mean[1]
    mz[g] += g_mean[2]
    s00[g] += g_cov[0]
    s01[g] += g_cov[1]
    s02[g] += g_cov[2]
    s11[g] += g_cov[4]
    s12[g] += g_cov[5]
    s22[g] += g_cov[8]


@njit(cache=True, _nrt=False, error_model="numpy", fastmath=True, pipeline_class=NoAlias)
def _project_bwd_chunk(start, means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, radii,
                       colors, rws, g_means2d, g_conics, g_depths, g_colors, want_pose, g_means, g_quats, g_scales,
                       g_coeffs, pose_sums, mx, my, mz, s00, s01, s02, s11, s12, s22, basis, g_sh):
    """The backward of Gaussians start .. start + CHUNK - 1 (fewer at the end) over every camera.

    The geometry runs camera by camera in loops over Gaussians that LLVM vectorises, as in `_project_chunk`: the
    sums go into [N] arrays (mx .. s22: the mean, and the upper triangle of the world covariance), and a Gaussian
    a camera does not draw adds zeros rather than branching. The SH backward then runs a Gaussian at a time and skips
    those. g_means, g_quats and g_scales are flattened (`_put`); pose_sums [C, chunks, 15] gets this chunk's pose
    partials (d Rw 9, d t 3, d campos 3) if want_pose."""
    stop = min(radii.shape[1], start + CHUNK)
    chunk = start // CHUNK
    first, last = np.uint64(start), np.uint64(stop)  # unsigned: no wraparound select, which keeps LLVM from seeing
    # that a loop's loads and stores of mx[g] .. s22[g] are to the same element
    for g in range(first, last):
        mx[g], my[g], mz[g] = 0.0, 0.0, 0.0
        s00[g], s01[g], s02[g], s11[g], s12[g], s22[g] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for c in range(viewmats.shape[0]):
        rw = _camera_rotation(rws, c)
        if want_pose:  # two loops: with the test inside one, LLVM keeps it scalar (0.78 -> 1.23 ms at 20k)
            for g in range(first, last):
                g_mean, g_cov, g_rw, g_t = _geometry_bwd(c, g, means, quats, scales, viewmats, Ks, width, height,
                                                         radii, g_means2d, g_conics, g_depths, rw)
                _accumulate(g, g_mean, g_cov, mx, my, mz, s00, s01, s02, s11, s12, s22)
                for k in range(9):
                    pose_sums[c, chunk, k] += g_rw[k]
                for k in range(3):
                    pose_sums[c, chunk, 9 + k] += g_t[k]
        else:
            for g in range(first, last):
                g_mean, g_cov, _, _ = _geometry_bwd(c, g, means, quats, scales, viewmats, Ks, width, height, radii,
                                                    g_means2d, g_conics, g_depths, rw)
                _accumulate(g, g_mean, g_cov, mx, my, mz, s00, s01, s02, s11, s12, s22)
    used = (sh_degree + 1) ** 2 if sh_degree >= 0 else 0
    for g in range(start, stop):
        gu = np.uint64(g)
        for k in range(3 * used):
            g_sh[k] = 0.0  # summed here, in cache, so that g_coeffs is written once and never zeroed
        for c in range(viewmats.shape[0] if used else 0):
            g_r = g_colors[c, g, 0] if colors[c, g, 0] > 0.0 else 0.0  # no gradient where the colour was clamped to 0
            g_g = g_colors[c, g, 1] if colors[c, g, 1] > 0.0 else 0.0
            g_b = g_colors[c, g, 2] if colors[c, g, 2] > 0.0 else 0.0
            if radii[c, g] <= 0 or (g_r == 0.0 and g_g == 0.0 and g_b == 0.0):
                continue  # hidden in this view (the back of the stone, most of the NGS noise): about half of them
            d0, d1, d2 = (_at(means, gu, 3, 0) - campos[c, 0], _at(means, gu, 3, 1) - campos[c, 1],
                          _at(means, gu, 3, 2) - campos[c, 2])
            nd = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            u0, u1, u2 = d0 / nd, d1 / nd, d2 / nd
            _sh_basis(u0, u1, u2, basis)
            bx, by, bz = _sh_basis_grad(u0, u1, u2)
            gd0, gd1, gd2 = 0.0, 0.0, 0.0
            for k in range(used):
                g_sh[3 * k] += basis[k] * g_r
                g_sh[3 * k + 1] += basis[k] * g_g
                g_sh[3 * k + 2] += basis[k] * g_b
                g_basis = coeffs[g, k, 0] * g_r + coeffs[g, k, 1] * g_g + coeffs[g, k, 2] * g_b
                gd0 += bx[k] * g_basis
                gd1 += by[k] * g_basis
                gd2 += bz[k] * g_basis
            dot = u0 * gd0 + u1 * gd1 + u2 * gd2
            gm0, gm1, gm2 = (gd0 - u0 * dot) / nd, (gd1 - u1 * dot) / nd, (gd2 - u2 * dot) / nd
            mx[g] += gm0
            my[g] += gm1
            mz[g] += gm2
            if want_pose:
                pose_sums[c, chunk, 12] -= gm0
                pose_sums[c, chunk, 13] -= gm1
                pose_sums[c, chunk, 14] -= gm2
        for k in range(g_coeffs.shape[1]):
            for i in range(3):
                g_coeffs[g, k, i] = g_sh[3 * k + i] if k < used else 0.0
    for g in range(first, last):
        _put(g_means, g, (mx[g], my[g], mz[g]))
        g_quat, g_scale = _cov_to_params(_at(quats, g, 4, 0), _at(quats, g, 4, 1), _at(quats, g, 4, 2),
                                         _at(quats, g, 4, 3), _at(scales, g, 3, 0), _at(scales, g, 3, 1),
                                         _at(scales, g, 3, 2), (s00[g], s01[g], s02[g], s11[g], s12[g], s22[g]))
        _put(g_quats, g, g_quat)
        _put(g_scales, g, g_scale)


@njit(parallel=PRANGE_ONLY, cache=True, error_model="numpy", fastmath=True)
def project_bwd(means, quats, scales, coeffs, sh_degree, viewmats, Ks, campos, width, height, radii, colors,
                g_means2d, g_conics, g_depths, g_colors, want_pose=True):
    """-> g_means [N,3], g_quats [N,4], g_scales [N,3], g_coeffs [N,K,3], g_viewmats [C,4,4], g_campos [C,3]
    (the last two zero unless want_pose: training poses are constants, so their partials are skipped)."""
    c_n, n = viewmats.shape[0], means.shape[0]
    chunks = (n + CHUNK - 1) // CHUNK
    dt = means.dtype
    g_means = np.empty((n, 3), dt)  # each Gaussian's rows are written in its chunk: np.zeros is a serial memset
    g_quats = np.empty((n, 4), dt)
    g_scales = np.empty((n, 3), dt)
    g_coeffs = np.empty(coeffs.shape, dt)
    flat = (g_means.reshape(3 * n), g_quats.reshape(4 * n), g_scales.reshape(3 * n))  # views, for `_put`
    flat_in = (means.reshape(3 * n), quats.reshape(4 * n), scales.reshape(3 * n))      # and for `_at`
    flat_up = (g_means2d.reshape(2 * c_n * n), g_conics.reshape(3 * c_n * n))
    rws = _rotations(viewmats)
    pose_sums = np.zeros((c_n, chunks if want_pose else 0, 15))  # per camera and chunk, summed in a fixed order
    sums = (np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n),
            np.empty(n))
    for chunk in prange(chunks):
        _project_bwd_chunk(chunk * CHUNK, *flat_in, coeffs, sh_degree, viewmats, Ks, campos, width, height, radii,
                           colors, rws, *flat_up, g_depths, g_colors, want_pose, *flat, g_coeffs, pose_sums, *sums,
                           np.empty(16), np.empty(48))
    pose = np.zeros((c_n, 15))  # loops, not pose_sums.sum(axis=1): that compiles error paths and strings for seconds
    for c in range(c_n):
        for chunk in range(pose_sums.shape[1]):
            for k in range(15):
                pose[c, k] += pose_sums[c, chunk, k]
    g_viewmats = np.zeros((c_n, 4, 4), dt)
    g_campos = np.zeros((c_n, 3), dt)
    for c in range(c_n):
        for i in range(3):
            for j in range(3):
                g_viewmats[c, i, j] = pose[c, 3 * i + j]
            g_viewmats[c, i, 3] = pose[c, 9 + i]
            g_campos[c, i] = pose[c, 12 + i]
    return g_means, g_quats, g_scales, g_coeffs, g_viewmats, g_campos
