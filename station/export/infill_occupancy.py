"""The body the NGS infill stands for, as an occupancy field the mesher can use.

The noise Gaussians sit on cell centres of nested, aligned grids (cell edge h = 2 x their scale;
a coarse cell is exactly 2x2x2.. finer cells), so painting each one's cell onto the finest
lattice recovers the infill as a voxel set without any fitting. Training erodes that set a few
fine cells away from the surface (so noise never pokes through it); growing it back by the same
number of cells gives the body the surface encloses. That grown body fills the mesher's
unobserved interior and the unseen bottom, and its volume is what the gate compares with the
mesh's. The turntable plate (z = 0) bounds it from below: nothing stands under the plate.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from station.errors import BadInputError
from station.export.mesh import VoxelGrid

MAX_LATTICE_CELLS = 384**3


def infill_lattice(means: np.ndarray, scales: np.ndarray, margin_cells: int) -> tuple[np.ndarray, VoxelGrid]:
    """Paint every infill cell onto the finest lattice: (occupied [X, Y, Z] bool, its VoxelGrid).

    means [M, 3] cell centres; scales [M] isotropic, half a cell edge. `margin_cells` of empty
    lattice surround the infill so it can be grown without touching the border.
    """
    means = np.asarray(means, np.float64)
    edges = 2.0 * np.asarray(scales, np.float64)  # [M] cell edge h of each noise Gaussian
    if means.ndim != 2 or means.shape[1] != 3 or edges.shape != (len(means),) or len(means) == 0:
        raise BadInputError(f"infill: means {means.shape} and scales {edges.shape} must be [M>0, 3] and [M]")
    if not (np.isfinite(means).all() and np.isfinite(edges).all() and (edges > 0).all()):
        raise BadInputError("infill: means or scales are not finite and positive")
    fine = float(edges.min())
    ratios = np.round(edges / fine).astype(np.int64)  # [M] fine cells per coarse-cell edge
    if np.abs(ratios * fine - edges).max() > 1e-3 * fine:
        raise BadInputError("infill: cell sizes are not integer multiples of the finest; not a nested NGS infill")
    corner = means - edges[:, None] / 2  # [M, 3] low corner of each cell
    origin = corner.min(axis=0) - margin_cells * fine  # low corner of the lattice
    first = np.round((corner - origin) / fine).astype(np.int64)  # [M, 3] first fine cell
    shape = np.max(first + ratios[:, None], axis=0) + margin_cells
    if np.prod(shape.astype(np.float64)) > MAX_LATTICE_CELLS:
        raise BadInputError(f"infill lattice {shape.tolist()} is too large to paint")
    occupied = np.zeros(tuple(int(s) for s in shape), bool)
    for ratio in np.unique(ratios):
        block = first[ratios == ratio]  # [K, 3]
        offsets = np.stack(np.meshgrid(*[np.arange(ratio)] * 3, indexing="ij"), -1).reshape(-1, 3)  # [r^3, 3]
        cells = (block[:, None, :] + offsets[None]).reshape(-1, 3)
        occupied[tuple(cells.T)] = True
    grid = VoxelGrid(tuple((origin + fine / 2).tolist()), fine, occupied.shape)
    return occupied, grid


def infill_body(
    means: np.ndarray, scales: np.ndarray, grow_cells: int, plate_z: float | None = 0.0
) -> tuple[np.ndarray, VoxelGrid]:
    """The infill grown back by `grow_cells` fine cells and cut at the plate: (occupancy [X, Y, Z]
    float32 in {0, 1}, its VoxelGrid)."""
    if grow_cells < 0:
        raise BadInputError(f"infill growth must be >= 0 cells, got {grow_cells}")
    occupied, grid = infill_lattice(means, scales, margin_cells=grow_cells + 2)
    if grow_cells:
        occupied = ndimage.binary_dilation(occupied, structure=np.ones((3, 3, 3), bool), iterations=grow_cells)
    if plate_z is not None:
        occupied[:, :, grid.axes()[2] < plate_z] = False
    return occupied.astype(np.float32), grid


def body_volume(occupancy: np.ndarray, grid: VoxelGrid) -> float:
    """Volume in m^3 of a {0, 1} (or fractional) occupancy field."""
    return float(occupancy.sum()) * grid.voxel_size**3
