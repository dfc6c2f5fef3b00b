"""Visual hull: a starting cloud carved from the masks when SfM finds too few points, and the
silhouette other rings predict for a view (cross_view.py).

Also the camera-set geometry it needs (where a ring of cameras looks, which way is up), shared
with the pure-SfM gauge and the importers.

A textureless stone gives SIFT almost nothing to match, but its silhouettes are still sharp
and the rig poses are still exact, so carving a voxel grid with every mask gives a cloud that
hugs the stone (from outside: concavities are filled) for the splats to start from.
"""

from __future__ import annotations

import numpy as np

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
    alive = np.arange(len(grid))  # voxels not yet carved away: each view only projects these
    seen_count = np.zeros(len(grid), dtype=np.int64)
    misses = np.zeros(len(grid), dtype=np.int64)
    colour_sum = np.zeros((len(grid), 3)) if images is not None else None
    colour_n = np.zeros(len(grid))
    k = intr.matrix().astype(np.float32)
    for i, (c2w, mask) in enumerate(zip(c2ws, masks)):
        w2c = np.linalg.inv(c2w).astype(np.float32)
        cam = grid[alive].astype(np.float32) @ w2c[:3, :3].T + w2c[:3, 3]  # [A, 3]
        front = cam[:, 2] > 1e-6
        uvw = cam @ k.T
        z = np.where(front, uvw[:, 2], 1.0)
        u = np.floor(uvw[:, 0] / z).astype(np.int64)
        v = np.floor(uvw[:, 1] / z).astype(np.int64)
        seen = front & (u >= 0) & (u < mask.shape[1]) & (v >= 0) & (v < mask.shape[0])
        hit = np.zeros(len(alive), dtype=bool)
        hit[seen] = mask[v[seen], u[seen]]
        seen_count[alive[seen]] += 1
        if colour_sum is not None:
            colour_sum[alive[hit]] += images[i][v[hit], u[hit], :3]
            colour_n[alive[hit]] += 1
        missed = seen & ~hit  # a voxel outside the frame is not evidence against it
        missed_ids = alive[missed]
        misses[missed_ids] += 1
        keep = ~missed
        keep[missed] = misses[missed_ids] <= max_misses  # only the voxels this view missed can drop out
        alive = alive[keep]
    inside = np.zeros(len(grid), dtype=bool)
    inside[alive] = True
    inside &= seen_count >= max(2, len(c2ws) // 2)  # ...but a voxel few views see is not evidence for it
    colours = colour_sum / np.maximum(colour_n, 1)[:, None] if colour_sum is not None else None
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
