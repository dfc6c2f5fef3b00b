"""numba kernels of the CPU rasteriser: tile binning, forward compositing, backward, the depth-pruning query.

Layout follows gsplat: every (tile, Gaussian) intersection sits in a per-tile, depth-sorted list. Tiles
run in parallel (prange). A tile's pixels are stored in strips, each row-major, so the rows of the strips a
Gaussian reaches are one contiguous run; the loop over them is branch-free (0/1 masks, not selects) and LLVM
vectorises it. `fast=True` uses a polynomial exp (rel. error ~7e-7, float32) because math.exp blocks
vectorisation; float64 callers (gradcheck) pass fast=False for math.exp. The forward records the rows of
each strip an intersection composited in; the backward walks only those, gives every intersection its own
gradient slot and reduces them per Gaussian in a fixed order: no atomics, deterministic.
Helpers that take arrays run without NRT (`_nrt=False`; none allocates): with it, every array argument of a
call in the per-intersection loops costs an atomic reference-count pair.
Keep every kernel and its helpers in this one module (numba's cache key).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange
from numba.core import types
from numba.extending import intrinsic

from station.ngs import conventions
from station.ngs._parallel import PRANGE_ONLY, NoAlias
from station.ngs.conventions import TILE

TILE_PIX = TILE * TILE
STRIP = 16  # pixels across a strip: a whole tile row, one AVX-512 vector of float32. 8-wide strips made twice
# the loops, each half as long, and a slower step (bench/raster.py --against)
STRIPS = TILE // STRIP
STRIP_PIX = TILE * STRIP
# float32 constants: a float64 literal would promote float32 arithmetic to float64 (half the SIMD width);
# with float64 inputs they promote harmlessly.
F = np.float32
ZERO, HALF, ONE = F(0.0), F(0.5), F(1.0)
ALPHA_MAX = F(conventions.ALPHA_MAX)
ALPHA_MIN = F(conventions.ALPHA_MIN)
T_STOP = F(conventions.T_STOP)
LOG2E = 1.4426950408889634
LOG2_FLOOR = F(-30.0 * LOG2E)  # exp(-30): far below any alpha that composites
BIG = 1e30
# 2 ** u on [0, 1), degree 5: a relative-error fit (reweighted least squares on Chebyshev nodes), max error 1.9e-7
# in float32 Horner, its mean held at -3.4e-8: float32 log2(e) is 1.3e-8 low, which raises exp(-sigma) by 1.3e-8 per
# unit of sigma, and the two cancel over the sigma where alpha can reach 1/255. Fitting 2 ** u itself, not sqrt(2)
# exp(f) on a centred range, saves the range's shift and scale, and a degree, at the same error
POLY = tuple(F(c) for c in (0.9999998807907104, 0.6931539177894592, 0.2401484251022339, 0.05583389475941658,
                            0.008987758308649063, 0.001875926274806261))
RGB = 3  # feature channels the compositing loops carry themselves; any others get a loop each


@njit(cache=True)
def _tile_rect(u, v, r, tw, th):
    """gsplat's isect rule: tiles [x0, x1) x [y0, y1) touched by a Gaussian of radius r at (u, v)."""
    x0 = min(max(int(math.floor((u - r) / TILE)), 0), tw)
    x1 = min(max(int(math.ceil((u + r) / TILE)), 0), tw)
    y0 = min(max(int(math.floor((v - r) / TILE)), 0), th)
    y1 = min(max(int(math.ceil((v + r) / TILE)), 0), th)
    return x0, y0, x1, y1


@njit(cache=True)
def _hit_rect(u, v, r, a, b, c, sig_max, tw, th):
    """gsplat's tile rectangle of radius r, cut to the bounding box of the ellipse sigma <= sig_max (padded):
    tiles outside it have no hits in `_row_hits` anyway, and fewer rows are tested."""
    x0, y0, x1, y1 = _tile_rect(u, v, r, tw, th)
    det = a * c - b * b
    if a <= 0.0 or c <= 0.0 or det <= 0.0:
        return x0, y0, x1, y1
    ex = math.sqrt(2.0 * sig_max * c / det) * 1.01 + 0.05
    ey = math.sqrt(2.0 * sig_max * a / det) * 1.01 + 0.05
    bx0 = min(max(int(math.floor((u - ex - 0.5) / TILE)), 0), tw)
    bx1 = min(max(int(math.floor((u + ex - 0.5) / TILE)) + 1, 0), tw)
    by0 = min(max(int(math.floor((v - ey - 0.5) / TILE)), 0), th)
    by1 = min(max(int(math.floor((v + ey - 0.5) / TILE)) + 1, 0), th)
    return max(x0, bx0), max(y0, by0), max(min(x1, bx1), max(x0, bx0)), max(min(y1, by1), max(y0, by0))


@njit(cache=True)
def _sig_max(opacity):
    """Largest sigma at which opacity * exp(-sigma) can still reach 1/255 (with a safety margin); -1 if never."""
    if opacity * 255.0 < 1.0 - 1e-6:
        return -1.0
    return math.log(max(opacity * 255.0, 1.0)) + 1e-3


@njit(cache=True)
def _extent(a, c, det, sig_max):
    """Half-width along one axis in pixels of the ellipse sigma <= sig_max (c: the conic's other diagonal term),
    padded for float32 rounding of sigma in the compositing loops; BIG for a conic that is not positive
    definite, 0 for a Gaussian never visible."""
    if sig_max < 0.0:
        return 0.0
    if a <= 0.0 or c <= 0.0 or det <= 0.0:
        return BIG
    return math.sqrt(2.0 * sig_max * c / det) * 1.01 + 0.05


@njit(cache=True)
def _pixel_range(m, ext, lo, hi):
    """Pixels [i0, i1) of [lo, hi) whose centres lie within ext of m (ext may be BIG); empty as (i0, i0)."""
    first = min(max(m - ext - 0.5, lo - 1.0), hi + 1.0)
    last = min(max(m + ext - 0.5, lo - 1.0), hi + 1.0)
    i0 = max(int(math.ceil(first)), lo)
    return i0, max(min(int(math.floor(last)) + 1, hi), i0)


@njit(cache=True)
def _span(m, ext, origin):
    """Tile-local rows (or columns) [i0, i1) whose pixel centres lie within ext of m: only they can reach alpha
    >= 1/255, so compositing skips the others (exactly: they would add nothing)."""
    return _pixel_range(m - origin, ext, 0, TILE)


@njit(cache=True, _nrt=False)
def _reach(means2d, extents, g, x0, y0):
    """Tile-local rows [r0, r1) and strips [s0, s1) of the tile at pixel (x0, y0) that Gaussian g can reach."""
    r0, r1 = _span(means2d[g, 1], extents[g, 1], y0)
    c0, c1 = _span(means2d[g, 0], extents[g, 0], x0)
    if c1 <= c0:
        return r0, r1, 0, 0
    return r0, r1, c0 // STRIP, (c1 + STRIP - 1) // STRIP


@njit(cache=True)
def _pixels(s, r0, r1):
    """Tile-local pixels [p0, p1) of rows [r0, r1) in strip s. Unsigned, because numba wraps a possibly negative
    signed index on every access, which stops LLVM from vectorising the loops."""
    base = s * STRIP_PIX
    return np.uint64(base + r0 * STRIP), np.uint64(base + max(r1, r0) * STRIP)


U8, RADIX_MASK = np.uint64(8), np.uint64(255)
I32_MAX = np.int32(2**31 - 1)
SORT_CHUNKS = 16  # parallel chunks of binning's counting sort
NOT_POSITIVE = (0.0, -1.0, 0.0, 0.0, 0.0)  # `_ellipse_rows` of a conic that is not positive definite
KEPT_ROWS = 4  # tile rows of a Gaussian whose hits binning keeps from its first pass; it recomputes any others


@njit(cache=True)
def _order_keys(depths):
    """uint64 keys in the depths' order: the float bits with the sign bit set, or all bits flipped when negative.
    float32 depths give 32-bit keys (the high half zero), so their sort needs at most four passes. + 0.0 makes
    -0.0 tie with 0.0."""
    n = depths.shape[0]
    keys = np.empty(n, np.uint64)
    if depths.itemsize == 4:
        bits32 = (depths + np.float32(0.0)).view(np.uint32)
        top32 = np.uint32(1) << np.uint32(31)
        for i in range(n):
            b = bits32[i]
            keys[i] = np.uint64(~b if b >= top32 else b | top32)
        return keys
    bits = (depths.astype(np.float64) + 0.0).view(np.uint64)
    top = np.uint64(1) << np.uint64(63)
    for i in range(n):
        b = bits[i]
        keys[i] = ~b if b >= top else b | top
    return keys


@njit(cache=True)
def depth_order(depths):
    """Stable argsort of depths (ties keep index order, as a stable merge sort): LSD radix sort, 8 bits a pass,
    on order-preserving unsigned keys; a pass whose digit every key shares (the unused high half of float32
    keys, the exponent byte of depths in a narrow range) is skipped."""
    n = depths.shape[0]
    keys = _order_keys(depths)
    same_bits = ~np.uint64(0)
    for i in range(n):
        same_bits &= ~(keys[i] ^ keys[0])
    order = np.arange(n)
    scratch = np.empty(n, np.int64)
    for pass_ in range(8):
        shift = np.uint64(pass_) * U8
        if (~same_bits >> shift) & RADIX_MASK == np.uint64(0):
            continue
        counts = np.zeros(257, np.int64)
        for i in range(n):
            counts[((keys[i] >> shift) & RADIX_MASK) + np.uint64(1)] += 1
        for d in range(256):
            counts[d + 1] += counts[d]
        for i in range(n):
            g = order[i]
            d = (keys[g] >> shift) & RADIX_MASK
            scratch[counts[d]] = g
            counts[d] += 1
        order, scratch = scratch, order
    return order


@njit(cache=True)
def _ellipse_rows(a, b, c, sig_max):
    """What `_row_hits` needs of the ellipse sigma <= sig_max, once a Gaussian: 1/a, det, 2 a sig_max, its reach in
    dy, and the dy at which it is widest (towards +dx at -turn, -dx at +turn). det <= 0: not positive definite."""
    det = a * c - b * b
    if a <= 0.0 or c <= 0.0 or det <= 0.0:
        return NOT_POSITIVE
    return 1.0 / a, det, 2.0 * a * sig_max, math.sqrt(2.0 * sig_max * a / det), b * math.sqrt(2.0 * sig_max / (c * det))


@njit(cache=True)
def _row_hits(u, v, b, ellipse, ty, x0, x1):
    """Tiles [tx0, tx1) of [x0, x1) in tile row ty whose pixel-centre rectangle meets the ellipse sigma <= sig_max:
    exact culling (never drops a pixel that would composite the Gaussian at alpha >= 1/255), about 2-3x fewer
    intersections than gsplat's 3-sigma rectangle. The ellipse's slice through the row's band of pixel centres is
    convex, so its x-extent is one interval: two square roots a row, not a test a tile. All of [x0, x1) for a conic
    that is not positive definite."""
    inv_a, det, two_as, reach_y, turn = ellipse
    if det <= 0.0:
        return x0, x1
    lo = max(v - (ty * TILE + TILE - 0.5), -reach_y)  # the band's dy = v - y, cut to the ellipse's
    hi = min(v - (ty * TILE + 0.5), reach_y)
    if lo > hi:
        return x0, x0
    y_right = min(max(-turn, lo), hi)
    y_left = min(max(turn, lo), hi)
    dx_max = (-b * y_right + math.sqrt(max(two_as - det * y_right * y_right, 0.0))) * inv_a
    dx_min = (-b * y_left - math.sqrt(max(two_as - det * y_left * y_left, 0.0))) * inv_a
    if not (abs(dx_max) < math.inf and abs(dx_min) < math.inf):
        return x0, x1
    # pixel centres x = u - dx in [u - dx_max, u - dx_min]; clamped before the int conversion, which overflows
    tx0 = int(math.ceil(min(max((u - dx_max - (TILE - 0.5)) * (1.0 / TILE), float(x0)), float(x1))))
    tx1 = int(math.floor(min(max((u - dx_min - 0.5) * (1.0 / TILE), x0 - 1.0), x1 - 1.0))) + 1
    return tx0, max(tx1, tx0)


@njit(parallel=PRANGE_ONLY, cache=True)
def bin_gaussians(means2d, conics, opacities, radii, depths, width, height):
    """Per-tile depth-sorted intersection lists -> tile_offsets [T+1], isect_gid [M], extents [N, 2] (x and y
    half-widths, see `_extent`). Intersections are made in depth order, so sorting them by tile is a stable counting
    sort over sequential reads, in parallel chunks."""
    n = means2d.shape[0]
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    ntiles = tw * th
    counts = np.empty(n, np.int64)
    extents = np.empty((n, 2), np.float64)
    sig = np.empty(n, np.float64)
    rects = np.empty((n, 4), np.int32)  # tile rectangle x0 y0 x1 y1 of the rows to test (where counts > 0)
    spans = np.empty((n, KEPT_ROWS, 2), np.int32)  # the hits [tx0, tx1) of its first rows, for the second pass
    for g in prange(n):
        sig_max = _sig_max(opacities[g])
        sig[g] = sig_max
        ca, cb, cc = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
        extents[g, 0] = _extent(ca, cc, ca * cc - cb * cb, sig_max)
        extents[g, 1] = _extent(cc, ca, ca * cc - cb * cb, sig_max)
        counts[g] = 0
        if radii[g] > 0 and sig_max >= 0.0:
            u, v = float(means2d[g, 0]), float(means2d[g, 1])
            x0, y0, x1, y1 = _hit_rect(u, v, float(radii[g]), ca, cb, cc, sig_max, tw, th)
            rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = x0, y0, x1, y1
            ellipse = _ellipse_rows(ca, cb, cc, sig_max)
            hit = 0
            for r in range(y1 - y0):
                a0, a1 = _row_hits(u, v, cb, ellipse, y0 + r, x0, x1)
                if r < KEPT_ROWS:
                    spans[g, r, 0], spans[g, r, 1] = a0, a1
                hit += a1 - a0
            counts[g] = hit
    order = depth_order(depths)
    order_offsets = np.zeros(n + 1, np.int64)
    # where each Gaussian's intersections start, so the next pass can run in index order: its reads are sequential,
    # where depth order's miss the cache at 100k Gaussians
    first = np.empty(n, np.int64)
    for i in range(n):
        first[order[i]] = order_offsets[i]
        order_offsets[i + 1] = order_offsets[i] + counts[order[i]]
    m = order_offsets[n]
    isect_tile = np.empty(m, np.int32)
    for g in prange(n):
        if counts[g] > 0:
            x0, y0, x1, y1 = rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3]
            ca, cb, cc = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
            ellipse = _ellipse_rows(ca, cb, cc, sig[g]) if y1 - y0 > KEPT_ROWS else NOT_POSITIVE
            j = first[g]
            for r in range(y1 - y0):
                if r < KEPT_ROWS:
                    a0, a1 = spans[g, r, 0], spans[g, r, 1]
                else:
                    a0, a1 = _row_hits(float(means2d[g, 0]), float(means2d[g, 1]), cb, ellipse, y0 + r, x0, x1)
                for tx in range(a0, a1):
                    isect_tile[j] = (y0 + r) * tw + tx
                    j += 1
    chunks = max(1, min(SORT_CHUNKS, m // 32768))  # fixed, not the thread count: numba can't cache that call
    bounds = np.full(chunks + 1, n, np.int64)  # Gaussians [bounds[c], bounds[c + 1]): ~m / chunks intersections
    bounds[0] = 0
    ch = 1
    for i in range(n):
        while ch < chunks and order_offsets[i] >= (ch * m) // chunks:
            bounds[ch] = i
            ch += 1
    hist = np.zeros((chunks, ntiles), np.int64)
    for ch in prange(chunks):
        for j in range(order_offsets[bounds[ch]], order_offsets[bounds[ch + 1]]):
            hist[ch, isect_tile[j]] += 1
    tile_offsets = np.empty(ntiles + 1, np.int64)
    cursor = np.empty((chunks, ntiles), np.int64)
    run = 0
    for t in range(ntiles):
        tile_offsets[t] = run
        for ch in range(chunks):
            cursor[ch, t] = run
            run += hist[ch, t]
    tile_offsets[ntiles] = run
    isect_gid = np.empty(m, np.int32)
    for ch in prange(chunks):
        for i in range(bounds[ch], bounds[ch + 1]):
            g = order[i]
            for j in range(order_offsets[i], order_offsets[i + 1]):
                t = isect_tile[j]
                isect_gid[cursor[ch, t]] = g
                cursor[ch, t] += 1
    return tile_offsets, isect_gid, extents


@intrinsic
def _float32_from_bits(typingctx, bits):
    """The float32 whose bit pattern is the int32 `bits`: how the polynomial exp builds 2**k. A bitcast, where an
    int32 buffer viewed as float32 costs a store and a reload per pixel."""
    if bits != types.int32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.int32), codegen


@njit(fastmath=True, cache=True, _nrt=False)
def _alphas(mx, my, ca, cb, cc, op, px, py, alpha, expo, fast, p0, p1):
    """Alpha and exp(-sigma) of one Gaussian over a tile's pixels [p0, p1); sigma < 0 gives alpha 0."""
    if fast:
        # the conic scaled once so that the quadratic form is log2 exp(-sigma) itself
        qa, qb, qc = F(-0.5 * LOG2E) * ca, F(-LOG2E) * cb, F(-0.5 * LOG2E) * cc
        for p in range(p0, p1):
            dx = mx - px[p]
            dy = my - py[p]
            y = qa * dx * dx + qc * dy * dy + qb * dx * dy
            yc = max(min(y, ZERO), LOG2_FLOOR)
            kf = np.floor(yc)
            u = yc - kf
            poly = POLY[0] + u * (POLY[1] + u * (POLY[2] + u * (POLY[3] + u * (POLY[4] + u * POLY[5]))))
            two_k = _float32_from_bits(np.int32((np.int32(kf) + np.int32(127)) << np.int32(23)))
            expo[p] = poly * two_k if y <= ZERO else ZERO
            alpha[p] = min(ALPHA_MAX, op * expo[p])
    else:
        for p in range(p0, p1):
            dx = mx - px[p]
            dy = my - py[p]
            sig = HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            expo[p] = math.exp(-sig) if sig >= ZERO else ZERO
            alpha[p] = min(ALPHA_MAX, op * expo[p])


@njit(cache=True)
def _tile_pixels(t, tw, width, height, dtype):
    """Pixel centres of tile t, strip by strip (see STRIP), and whether each lies inside the image."""
    px = np.empty(TILE_PIX, dtype)
    py = np.empty(TILE_PIX, dtype)
    inside = np.empty(TILE_PIX, np.bool_)
    x0 = (t % tw) * TILE
    y0 = (t // tw) * TILE
    for p in range(TILE_PIX):
        x = x0 + (p // STRIP_PIX) * STRIP + p % STRIP
        y = y0 + (p % STRIP_PIX) // STRIP
        px[p] = x + 0.5
        py[p] = y + 0.5
        inside[p] = x < width and y < height
    return px, py, inside


@njit(cache=True, _nrt=False)
def _live_rows(state, live, rows):
    """Per strip, the rows [rows[s, 0], rows[s, 1]) from the first to the last holding a live pixel (its `state` is
    `live`; empty: none); rows outside are finished, so compositing skips them exactly. Returns whether any strip is
    live."""
    any_live = False
    for s in range(STRIPS):
        r0, r1 = TILE, 0
        for r in range(TILE):
            v = 0
            for q in range(STRIP):
                v += state[s * STRIP_PIX + r * STRIP + q] == live
            if v > 0:
                r0 = min(r0, r)
                r1 = r + 1
        rows[s, 0], rows[s, 1] = r0, max(r1, r0)
        any_live |= r1 > r0
    return any_live


@njit(cache=True, _nrt=False)
def _live_alphas(means2d, conics, opacities, g, s, r0, r1, rows, px, py, alpha, expo, fast):
    """Alphas of Gaussian g over its rows [r0, r1) of strip s that still hold a live pixel (`_live_rows`) ->
    those pixels [p0, p1), empty if none."""
    p0, p1 = _pixels(s, max(r0, rows[s, 0]), min(r1, rows[s, 1]))
    if p0 < p1:
        _alphas(means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g], px, py, alpha,
                expo, fast, p0, p1)
    return p0, p1


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def rasterize_fwd(means2d, conics, colors, opacities, tile_offsets, isect_gid, extents, width, height, fast):
    """Composite colors [N, D >= 3] front to back -> feats [H, W, D] (no background), T_final [H, W], n_proc [H, W]
    int32 (position in the tile list where the pixel stopped; the list length if it never did), taken [M, 2 * STRIPS]
    uint8 (per intersection and strip, the rows [first, last) where it composited a pixel: only there can the
    backward find a gradient; [0, 0) for none)."""
    dt = means2d.dtype
    d_ch = colors.shape[1]
    if d_ch < RGB:
        raise ValueError("rasterize_fwd: colors must have at least the three colour channels")
    tw = (width + TILE - 1) // TILE
    ntiles = tile_offsets.shape[0] - 1
    feats = np.empty((height, width, d_ch), dt)  # every pixel is written by its tile; `taken` is zeroed a tile at a
    t_final = np.empty((height, width), dt)      # time: np.zeros would be a serial memset
    n_proc = np.empty((height, width), np.int32)
    taken = np.empty((tile_offsets[ntiles], 2 * STRIPS), np.uint8)
    for t in prange(ntiles):
        start, end = tile_offsets[t], tile_offsets[t + 1]
        for i in range(start, end):
            for q in range(2 * STRIPS):
                taken[i, q] = 0
        px, py, inside = _tile_pixels(t, tw, width, height, dt)
        x0 = (t % tw) * TILE
        y0 = (t // tw) * TILE
        T = np.ones(TILE_PIX, dt)
        never = np.int32(end - start)
        stop_at = np.empty(TILE_PIX, np.int32)  # where each pixel stopped; `never` while it composites (is live)
        acc = np.zeros((d_ch, TILE_PIX), dt)
        alpha = np.empty(TILE_PIX, dt)
        expo = np.empty(TILE_PIX, dt)
        w = np.empty(TILE_PIX, dt)
        for p in range(TILE_PIX):
            stop_at[p] = never if inside[p] else np.int32(-1)  # outside the image: stopped before it starts
        rows = np.empty((STRIPS, 2), np.int64)  # per strip, the rows that still hold a live pixel
        _live_rows(stop_at, never, rows)
        for k in range(end - start):
            g = isect_gid[start + k]
            r0, r1, s0, s1 = _reach(means2d, extents, g, x0, y0)
            k32 = np.int32(k)
            red, green, blue = colors[g, 0], colors[g, 1], colors[g, 2]
            for s in range(s0, s1):
                p0, p1 = _live_alphas(means2d, conics, opacities, g, s, r0, r1, rows, px, py, alpha, expo, fast)
                if p0 >= p1:
                    continue
                first, last = I32_MAX, np.int32(-1)  # the first and last pixel composited: int32 min/max reductions
                for p in range(p0, p1):
                    a = alpha[p]
                    t = T[p]
                    at = a * t
                    valid = np.float32(a >= ALPHA_MIN) * np.float32(stop_at[p] == never)  # 0/1 masks: they vectorise
                    take = valid * np.float32(t - at > T_STOP)        # t (1 - a), as t - a t: one product fewer
                    wp = at * take
                    w[p] = wp
                    T[p] = t - wp
                    stop_at[p] = k32 if valid > take else stop_at[p]  # valid, not taken: the pixel stops here
                    q = np.int32(p)
                    first = min(first, q if take > ZERO else I32_MAX)
                    last = max(last, q if take > ZERO else np.int32(-1))
                    acc[0, p] += red * wp                               # the colour here, the other channels after
                    acc[1, p] += green * wp
                    acc[2, p] += blue * wp
                _record_taken(first, last, s, taken[start + k])
                for d in range(RGB, d_ch):
                    c = colors[g, d]
                    for p in range(p0, p1):
                        acc[d, p] += c * w[p]
            if k % 8 == 7 and not _live_rows(stop_at, never, rows):
                break
        for p in range(TILE_PIX):
            if inside[p]:
                x = int(px[p])
                y = int(py[p])
                t_final[y, x] = T[p]
                n_proc[y, x] = stop_at[p]
                for d in range(d_ch):
                    feats[y, x, d] = acc[d, p]
    return feats, t_final, n_proc, taken


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def median_depth_fwd(means2d, conics, opacities, depths, tile_offsets, isect_gid, extents, width, height,
                     alpha_level, fast):
    """Per pixel, the depth of the Gaussian whose compositing takes alpha to that pixel's `alpha_level` [H, W] or
    above -> [H, W] (+inf where it never does). Same skip and stop rules as rasterize_fwd; forward only (meshing,
    pruning)."""
    dt = means2d.dtype
    tw = (width + TILE - 1) // TILE
    ntiles = tile_offsets.shape[0] - 1
    out = np.full((height, width), np.inf, dt)
    for t in prange(ntiles):
        start, end = tile_offsets[t], tile_offsets[t + 1]
        px, py, inside = _tile_pixels(t, tw, width, height, dt)
        x0 = (t % tw) * TILE
        y0 = (t // tw) * TILE
        T = np.ones(TILE_PIX, dt)
        live = np.empty(TILE_PIX, dt)
        median = np.full(TILE_PIX, np.inf, dt)
        alpha = np.empty(TILE_PIX, dt)
        expo = np.empty(TILE_PIX, dt)
        t_level = np.ones(TILE_PIX, dt)
        for p in range(TILE_PIX):
            live[p] = 1.0 if inside[p] else 0.0
            if inside[p]:
                t_level[p] = ONE - alpha_level[int(py[p]), int(px[p])]
        rows = np.empty((STRIPS, 2), np.int64)
        _live_rows(live, ONE, rows)
        for k in range(end - start):
            g = isect_gid[start + k]
            r0, r1, s0, s1 = _reach(means2d, extents, g, x0, y0)
            z = depths[g]
            for s in range(s0, s1):
                p0, p1 = _live_alphas(means2d, conics, opacities, g, s, r0, r1, rows, px, py, alpha, expo, fast)
                if p0 >= p1:
                    continue
                for p in range(p0, p1):
                    a = alpha[p]
                    t = T[p]
                    at = a * t
                    next_t = t - at                                    # as rasterize_fwd computes it
                    valid = np.float32(a >= ALPHA_MIN) * live[p]       # 0/1 masks, as in rasterize_fwd
                    take = valid * np.float32(next_t > T_STOP)
                    crossed = take * np.float32(next_t <= t_level[p]) * np.float32(t > t_level[p])
                    median[p] = z if crossed > ZERO else median[p]
                    T[p] = t - at * take
                    live[p] = ZERO if (valid > take) or T[p] <= t_level[p] else live[p]
            if k % 8 == 7 and not _live_rows(live, ONE, rows):
                break
        for p in range(TILE_PIX):
            if inside[p]:
                out[int(py[p]), int(px[p])] = median[p]
    return out


@njit(cache=True, _nrt=False)
def _record_taken(first, last, s, row):
    """Note in `row` (an intersection's `taken`) the rows of strip s from the one holding pixel `first` to the one
    holding pixel `last`: those it composited in. Two index reductions in the compositing loop find them,
    cheaper than summing each row's weights after it."""
    if first <= last:
        base = s * STRIP_PIX
        row[2 * s] = (int(first) - base) // STRIP
        row[2 * s + 1] = (int(last) - base) // STRIP + 1


@njit(cache=True, _nrt=False, forceinline=True)
def _taken_span(taken, i, s):
    """Tile-local pixels [p0, p1) of the rows in strip s that intersection i composited in (`rasterize_fwd`);
    empty if none."""
    return _pixels(s, int(taken[i, 2 * s]), int(taken[i, 2 * s + 1]))


@njit(fastmath=True, cache=True, _nrt=False, error_model="numpy", pipeline_class=NoAlias)
def _bwd_tile(start, kmax, means2d, conics, colors, opacities, isect_gid, taken, slots, px, py, T, limit, ga_tn, go,
              rest, alpha, expo, w, g_col, fast):
    """The backward of one tile's first `kmax` intersections into their `slots` rows, on the tile's per-pixel
    state. Its own function so that its arrays are `noalias`: in the prange body LLVM checks them for overlap
    before every strip's vector loop."""
    d_ch = colors.shape[1]
    for k in range(kmax):
        i = start + k
        k32 = np.int32(k)
        g = isect_gid[i]
        mx, my = means2d[g, 0], means2d[g, 1]
        ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
        op = opacities[g]
        red, green, blue = colors[g, 0], colors[g, 1], colors[g, 2]
        for s in range(STRIPS):
            p0, p1 = _taken_span(taken, i, s)
            if p0 >= p1:
                continue
            _alphas(mx, my, ca, cb, cc, op, px, py, alpha, expo, fast, p0, p1)
            for d in range(RGB, d_ch):  # the extra channels' share of g_col; the colour's is added inline
                c = colors[g, d]
                keep = ZERO if d == RGB else ONE  # the first drops the last intersection's share
                for p in range(p0, p1):
                    g_col[p] = keep * g_col[p] + go[d, p] * c
            g_red = ZERO
            g_green = ZERO
            g_blue = ZERO
            g_op = ZERO
            s_x = ZERO  # sums of d loss / d sigma times dx, dy and their products: the conic's terms come after
            s_y = ZERO
            s_xx = ZERO
            s_xy = ZERO
            s_yy = ZERO
            for p in range(p0, p1):  # one pass: no per-pixel intermediates stored and read back
                a = alpha[p]
                t = T[p]
                take = np.float32(a >= ALPHA_MIN) * np.float32(k32 < limit[p])  # a 0/1 mask: it vectorises
                inv = take / (ONE - a)
                t_take = t * take
                wp = a * t_take
                w[p] = wp
                g_red += go[0, p] * wp
                g_green += go[1, p] * wp
                g_blue += go[2, p] * wp
                T[p] = t - wp                                          # as the forward's
                gc = go[0, p] * red + go[1, p] * green + go[2, p] * blue + g_col[p]
                rest[p] -= wp * gc
                unclamped = np.float32(a < ALPHA_MAX)                  # no gradient through the clamp
                gd = (inv * (ga_tn[p] - rest[p]) + t_take * gc) * unclamped
                g_op += gd * expo[p]
                g_sig = gd * a                                         # minus d loss / d sigma
                dx = mx - px[p]
                dy = my - py[p]
                s_x += g_sig * dx
                s_y += g_sig * dy
                s_xx += g_sig * dx * dx
                s_xy += g_sig * dx * dy
                s_yy += g_sig * dy * dy
            slots[i, 5] += g_red
            slots[i, 6] += g_green
            slots[i, 7] += g_blue
            for d in range(RGB, d_ch):
                acc_c = ZERO
                for p in range(p0, p1):
                    acc_c += go[d, p] * w[p]
                slots[i, 5 + d] += acc_c
            slots[i, 0] -= ca * s_x + cb * s_y
            slots[i, 1] -= cc * s_y + cb * s_x
            slots[i, 2] -= HALF * s_xx
            slots[i, 3] -= s_xy
            slots[i, 4] -= HALF * s_yy
            slots[i, 5 + d_ch] += g_op


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def rasterize_bwd(means2d, conics, colors, opacities, background, tile_offsets, isect_gid, taken, width, height,
                  feats, t_final, n_proc, g_feats, g_alpha, fast):
    """Per-intersection gradients in list order -> slots [M, 6 + D]: d means2d (2), d conic (3), d colour (D),
    d opacity (1). Walks only the rows the forward composited in (`taken`); the rest add nothing."""
    dt = means2d.dtype
    d_ch = colors.shape[1]
    if d_ch < RGB:
        raise ValueError("rasterize_bwd: colors must have at least the three colour channels")
    tw = (width + TILE - 1) // TILE
    ntiles = tile_offsets.shape[0] - 1
    m = isect_gid.shape[0]
    slots = np.empty((m, 6 + d_ch), dt)  # zeroed a tile at a time below: np.zeros is a serial memset, 24 MB at 100k
    for t in prange(ntiles):
        start, end = tile_offsets[t], tile_offsets[t + 1]
        if end == start:
            continue
        for i in range(start, end):
            for q in range(6 + d_ch):
                slots[i, q] = 0.0
        px, py, inside = _tile_pixels(t, tw, width, height, dt)
        T = np.ones(TILE_PIX, dt)
        limit = np.zeros(TILE_PIX, np.int32)
        ga_tn = np.zeros(TILE_PIX, dt)  # d loss / d alpha times T_final: the alpha loss's share of each pixel's term
        go = np.zeros((d_ch, TILE_PIX), dt)
        rest = np.zeros(TILE_PIX, dt)  # sum over channels of d loss / d colour times what is left behind the list
        alpha = np.empty(TILE_PIX, dt)
        expo = np.empty(TILE_PIX, dt)
        w = np.empty(TILE_PIX, dt)
        g_col = np.zeros(TILE_PIX, dt)  # d loss / d extra channels . this Gaussian's, per pixel
        kmax = np.int64(0)  # not a literal 0: numba would compile _bwd_tile once more for Literal[int](0)
        for p in range(TILE_PIX):
            if inside[p]:
                x = int(px[p])
                y = int(py[p])
                limit[p] = n_proc[y, x]
                kmax = max(kmax, n_proc[y, x])
                ga_tn[p] = g_alpha[y, x] * t_final[y, x]
                for d in range(d_ch):
                    go[d, p] = g_feats[y, x, d]
                    rest[p] += g_feats[y, x, d] * (feats[y, x, d] + t_final[y, x] * background[d])
        _bwd_tile(start, kmax, means2d, conics, colors, opacities, isect_gid, taken, slots, px, py, T, limit, ga_tn,
                  go, rest, alpha, expo, w, g_col, fast)
    return slots


@njit(cache=True)
def reduce_per_gaussian(slot_grads, isect_gid, n):
    """Sum per-intersection gradient rows [M, 6 + D] per Gaussian, each in tile order (deterministic) -> d means2d
    [N, 2], d conic [N, 3], d colour [N, D], d opacity [N]. One sequential pass adding into [N, 6 + D] rows, which
    stay in cache (faster at 100k Gaussians than a parallel loop per Gaussian, whose rows are random reads), then
    split into separate arrays: torch would copy each strided slice of the rows before the projection's backward."""
    kk = slot_grads.shape[1]
    rows = np.zeros((n, kk), slot_grads.dtype)
    for j in range(slot_grads.shape[0]):
        g = isect_gid[j]
        for q in range(kk):
            rows[g, q] += slot_grads[j, q]
    d_ch = kk - 6
    g_means2d = np.empty((n, 2), rows.dtype)
    g_conics = np.empty((n, 3), rows.dtype)
    g_colors = np.empty((n, d_ch), rows.dtype)
    g_opacities = np.empty(n, rows.dtype)
    for g in range(n):
        g_means2d[g, 0], g_means2d[g, 1] = rows[g, 0], rows[g, 1]
        g_conics[g, 0], g_conics[g, 1], g_conics[g, 2] = rows[g, 2], rows[g, 3], rows[g, 4]
        for d in range(d_ch):
            g_colors[g, d] = rows[g, 5 + d]
        g_opacities[g] = rows[g, 5 + d_ch]
    return g_means2d, g_conics, g_colors, g_opacities


@njit(cache=True)
def _top_exponent(bits, exponent, lo, hi):
    """Largest `bits & exponent` over bits[lo:hi]; unsigned indices, which let LLVM vectorise the max (see `_pixels`)."""
    top = exponent - exponent
    for i in range(np.uint64(lo), np.uint64(hi)):
        top = max(top, bits[i] & exponent)
    return top


@njit(parallel=PRANGE_ONLY, cache=True)
def all_finite(bits, exponent):
    """Whether no value of a float array, viewed as unsigned ints `bits`, has the all-ones `exponent` of inf and
    NaN. A max over the exponent bits vectorises and allocates nothing; np.isfinite builds an [N] bool array.
    Arrays under a million values take one thread: waking the pool costs more."""
    n = bits.shape[0]
    if n < 1 << 20:
        return _top_exponent(bits, exponent, 0, n) < exponent
    chunks = 16
    worst = np.zeros(chunks, bits.dtype)
    for ch in prange(chunks):
        worst[ch] = _top_exponent(bits, exponent, ch * n // chunks, (ch + 1) * n // chunks)
    return worst.max() < exponent


@njit(parallel=PRANGE_ONLY, fastmath=True, cache=True)
def seen_in_front(means2d, conics, opacities, radii, depths, width, height, limit):
    """Per Gaussian, whether some pixel sees it (alpha >= 1/255 inside its tiles: compositing's skip rule) at a
    depth below that pixel's `limit` [H, W] -> [N] bool. No stop rule: what lies in front counts even where other
    Gaussians have used up the transmittance. Walks each Gaussian's own footprint: no binning, no sort."""
    n = means2d.shape[0]
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    out = np.zeros(n, np.bool_)
    for g in prange(n):
        sig_max = _sig_max(opacities[g])
        if radii[g] <= 0 or sig_max < 0.0:
            continue
        u, v = float(means2d[g, 0]), float(means2d[g, 1])
        ca, cb, cc = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
        op, z = float(opacities[g]), depths[g]
        tx0, ty0, tx1, ty1 = _tile_rect(u, v, float(radii[g]), tw, th)
        x0, x1 = _pixel_range(u, _extent(ca, cc, ca * cc - cb * cb, sig_max), tx0 * TILE, min(tx1 * TILE, width))
        y0, y1 = _pixel_range(v, _extent(cc, ca, ca * cc - cb * cb, sig_max), ty0 * TILE, min(ty1 * TILE, height))
        for y in range(y0, y1):
            dy = v - (y + 0.5)
            for x in range(x0, x1):
                dx = u - (x + 0.5)
                sig = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                if sig >= 0.0 and z < limit[y, x] and op * math.exp(-sig) >= ALPHA_MIN:  # ALPHA_MAX is above it
                    out[g] = True
                    break
            if out[g]:
                break
    return out
