"""Visual hull: a starting cloud carved from the masks when SfM finds too few points, and the
silhouette other rings predict for a view (cross_view.py).

Also the camera-set geometry it needs (where a ring of cameras looks, which way is up), shared
with the pure-SfM gauge and the importers.

A textureless stone gives SIFT almost nothing to match, but its silhouettes are still sharp
and the rig poses are still exact, so carving a voxel grid with every mask gives a cloud that
hugs the stone (from outside: concavities are filled) for the splats to start from.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from station.formats.transforms import PinholeCamera


def convergence_point(c2ws: list[np.ndarray]) -> np.ndarray:
    """Least-squares point closest to every optical axis: where the cameras look."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c2w in c2ws:
        d = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ c2w[:3, 3]
    return np.linalg.lstsq(a, b, rcond=None)[0]


def ring_frame(c2ws: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (rows = new axes) and origin putting z along the camera ring's normal, cameras above."""
    centres = np.array([c[:3, 3] for c in c2ws])
    target = convergence_point(c2ws)
    _, _, vt = np.linalg.svd(centres - centres.mean(0))
    up = vt[2] if vt[2] @ (centres.mean(0) - target) >= 0 else -vt[2]
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - (helper @ up) * up
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up]), target


def view_bounds(c2ws: list[np.ndarray], intr: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box that holds everything every camera can see around the convergence point."""
    centre = convergence_point(c2ws)
    dist = float(np.median([np.linalg.norm(c[:3, 3] - centre) for c in c2ws]))
    half = dist * 0.5 * max(intr.width / intr.fx, intr.height / intr.fy)
    return centre - half, centre + half


def grid_points(lo: np.ndarray, hi: np.ndarray, resolution: int) -> np.ndarray:
    """Voxel centres [R^3, 3] of a resolution^3 grid spanning the box lo..hi, x slowest."""
    axes = [np.linspace(lo[i], hi[i], resolution) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def carve_grid(
    c2ws: list[np.ndarray],
    masks: list[np.ndarray],
    intr: PinholeCamera,
    grid: np.ndarray,
    images: list[np.ndarray] | None = None,
    max_misses: int = 0,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Which `grid` points [N, 3] lie inside every mask that sees them, but for at most `max_misses` of those
    masks [N] bool, and their mean colour [N, 3] over the views (when `images` are given)."""
    if len(c2ws) == 0:
        return np.zeros(len(grid), dtype=bool), (np.zeros((len(grid), 3)) if images is not None else None)
    # numba compiles the carve once per argument type: poses of any float width go in as float64, and the
    # colourless placeholder is uint8 like the images (8-bit RGB from every caller)
    w2cs = np.stack([np.linalg.inv(np.asarray(c2w, np.float64))[:3] for c2w in c2ws])
    stacked_masks, sizes = _stack_padded([np.asarray(m, dtype=bool) for m in masks])
    stacked_images = (_stack_padded([np.asarray(im)[..., :3] for im in images])[0] if images is not None
                      else np.zeros((1, 1, 1, 3), np.uint8))
    inside, colours = _carve(np.ascontiguousarray(grid, dtype=np.float64), w2cs, intr.matrix().astype(np.float64),
                             stacked_masks, sizes, stacked_images, images is not None, max_misses,
                             max(2, len(c2ws) // 2))
    return inside, colours if images is not None else None


def _stack_padded(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One [V, Hmax, Wmax, ...] array of the views' images, zero-padded, and each view's own [V, 2] (H, W)."""
    sizes = np.array([a.shape[:2] for a in arrays], dtype=np.int64)
    out = np.zeros((len(arrays), *sizes.max(0), *arrays[0].shape[2:]), dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0], : a.shape[1]] = a
    return out, sizes


@njit(inline="always")
def pixel_of(w2c, k, x, y, z):
    """(column, row, in front): the pixel the point (x, y, z) lands in through the camera `w2c` [3, 4] and `k`."""
    cz = w2c[2, 0] * x + w2c[2, 1] * y + w2c[2, 2] * z + w2c[2, 3]
    if cz <= 1e-6:
        return 0, 0, False
    cx = w2c[0, 0] * x + w2c[0, 1] * y + w2c[0, 2] * z + w2c[0, 3]
    cy = w2c[1, 0] * x + w2c[1, 1] * y + w2c[1, 2] * z + w2c[1, 3]
    w = k[2, 0] * cx + k[2, 1] * cy + k[2, 2] * cz
    column = math.floor((k[0, 0] * cx + k[0, 1] * cy + k[0, 2] * cz) / w)
    return column, math.floor((k[1, 0] * cx + k[1, 1] * cy + k[1, 2] * cz) / w), True


@njit(cache=True)
def draw_points(points, offsets, w2c, k, height, width):
    """[H, W] bool: the pixels the points [N, 3], each moved by every offset [O, 3], land in (in front of the camera).
    One loop, not a numpy pass per offset: every posed view of a scan projects a hull. It lives beside `pixel_of`:
    numba's cache does not see edits to a helper in another module."""
    silhouette = np.zeros((height, width), dtype=np.bool_)
    for i in range(points.shape[0]):
        for o in range(offsets.shape[0]):
            u, v, in_front = pixel_of(w2c, k, points[i, 0] + offsets[o, 0], points[i, 1] + offsets[o, 1],
                                      points[i, 2] + offsets[o, 2])
            if in_front and 0 <= u < width and 0 <= v < height:
                silhouette[v, u] = True
    return silhouette


@njit(parallel=True, cache=True)
def _carve(grid, w2cs, k, masks, sizes, images, with_colour, max_misses, min_seen):
    """Per voxel, the views in order until more than `max_misses` of those that see it call it background:
    the voxels a view carves away are never projected again, so most of the grid costs a few views."""
    n, views = grid.shape[0], w2cs.shape[0]
    inside = np.zeros(n, dtype=np.bool_)
    colours = np.zeros((n if with_colour else 0, 3))
    for i in prange(n):
        x, y, z = grid[i, 0], grid[i, 1], grid[i, 2]
        seen = 0
        misses = 0
        r = g = b = 0.0
        hits = 0
        for v in range(views):
            u, row, in_front = pixel_of(w2cs[v], k, x, y, z)
            if not in_front:
                continue
            if u < 0 or u >= sizes[v, 1] or row < 0 or row >= sizes[v, 0]:
                continue  # a voxel outside the frame is not evidence against it
            seen += 1
            if masks[v, row, u]:
                if with_colour:
                    r += images[v, row, u, 0]
                    g += images[v, row, u, 1]
                    b += images[v, row, u, 2]
                    hits += 1
            else:
                misses += 1
                if misses > max_misses:
                    break
        inside[i] = misses <= max_misses and seen >= min_seen  # a voxel few views see is not evidence for it
        if with_colour and hits > 0:
            colours[i, 0], colours[i, 1], colours[i, 2] = r / hits, g / hits, b / hits
    return inside, colours


def surface_voxels(inside: np.ndarray, resolution: int) -> np.ndarray:
    """Occupied voxels [R^3] bool with at least one empty face neighbour (or on the grid's edge)."""
    occ = inside.reshape((resolution,) * 3)
    padded = np.pad(occ, 1, constant_values=False)
    interior = occ.copy()
    for axis in range(3):
        for shift in (-1, 1):
            interior &= np.roll(padded, shift, axis=axis)[1:-1, 1:-1, 1:-1]
    return (occ & ~interior).reshape(-1)


def carve(
    c2ws: list[np.ndarray],
    masks: list[np.ndarray],
    images: list[np.ndarray],
    intr: PinholeCamera,
    resolution: int = 96,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface voxels of the visual hull [N, 3] and their mean colour over the views [N, 3] uint8."""
    grid = grid_points(*view_bounds(c2ws, intr), resolution)
    inside, colours = carve_grid(c2ws, masks, intr, grid, images)
    surface = surface_voxels(inside, resolution)
    return grid[surface], np.clip(colours[surface], 0, 255).astype(np.uint8)
