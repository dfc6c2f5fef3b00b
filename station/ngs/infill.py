"""The NGS infill: opaque noise Gaussians that fill the object's inside, never its outside.

Candidates come from multi-scale voxel levels inside the convex hull (Quickhull) of the surface
means. After each level, depth pruning removes noise that any training view sees before the
surface (or sees with no surface at all), and a 3D erosion pulls the new noise back from the
boundary. Levels are aligned on cell centres of nested grids, so a coarse cell is exactly its
2x2x2 finer cells (the reference's node grid drifts by up to one fine voxel per level).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import binary_erosion
from scipy.spatial import ConvexHull, QhullError

from station.errors import BadInputError
from station.ngs.raster import median_depth, rasterization, seen_in_front

RGBCMY = torch.tensor(
    [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 1.0, 1.0], [1.0, 0, 1.0], [1.0, 1.0, 0]]
)  # [6, 3]


@dataclass
class InfillConfig:
    levels: tuple[int, ...] = (32, 64, 128, 256)
    erosion_iters: tuple[int, ...] = (3, 4, 5, 6)
    first_opacity: float = 0.01  # noise opacity while pruning, first level
    finer_opacity: float = 0.005  # ... finer levels
    pad: float = 0.05  # bounding box padding per side
    prune_downscale: int = 4  # depth pruning renders at 1/4 resolution
    # Where the surface starts for depth pruning: its accumulated alpha reaching this (or half its alpha, where
    # less). The paper's first faint surface Gaussian (1/255) kept noise inside the diffuse layer of DTU's dark
    # cavities (docs/real-photos.md).
    surface_alpha: float = 0.5
    depth_prune: bool = True
    erosion: bool = True


@dataclass
class Infill:
    means: torch.Tensor  # [M, 3]
    scales: torch.Tensor  # [M] isotropic, linear
    levels: torch.Tensor  # [M] the grid resolution R each came from

    def __len__(self) -> int:
        return self.means.shape[0]

    def gaussians(self, opacity: float | torch.Tensor) -> dict[str, torch.Tensor]:
        """Rasteriser inputs with identity rotation; opacity a scalar or [M]."""
        m, device = len(self), self.means.device
        quats = torch.zeros(m, 4, device=device)
        quats[:, 0] = 1
        opacities = torch.as_tensor(opacity, dtype=torch.float32, device=device).expand(m).clone()
        return {"means": self.means, "quats": quats, "scales": self.scales[:, None].repeat(1, 3), "opacities": opacities}

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"means": self.means, "scales": self.scales, "levels": self.levels}

    @staticmethod
    def from_state_dict(data: dict) -> "Infill":
        return Infill(data["means"].float(), data["scales"].float(), data["levels"].long())

    def select(self, keep: torch.Tensor) -> "Infill":
        return Infill(self.means[keep], self.scales[keep], self.levels[keep])

    def to(self, device: torch.device | str) -> "Infill":
        return Infill(self.means.to(device), self.scales.to(device), self.levels.to(device))


@dataclass
class Camera:
    viewmat: torch.Tensor  # [4, 4] world-to-camera, OpenCV
    K: torch.Tensor  # [3, 3]
    width: int
    height: int


def random_rgbcmy(count: int, generator: torch.Generator, device: torch.device | str = "cpu") -> torch.Tensor:
    """[count, 3] colours drawn from {R, G, B, C, M, Y}, on `device` (drawn with the generator on its own)."""
    return RGBCMY[torch.randint(0, 6, (count,), generator=generator, device=generator.device).cpu()].to(device)


def core_points(points: np.ndarray, tail: float = 0.5, margin: float = 0.1) -> np.ndarray:
    """The means that can shape the hull: a far floater must not stretch it.

    One Gaussian densification flung ten object sizes away (seen on a 30k-Gaussian stone at the
    build step) widened the hull's box tenfold, so the coarse level had a handful of cells and erosion
    left no infill at all. Kept: points within `margin` of the robust extent (the `tail`% and
    100-`tail`% quantiles per axis) beyond that extent; a true extremity lies within it."""
    lo, hi = np.percentile(points, [tail, 100 - tail], axis=0)
    reach = margin * (hi - lo)
    keep = np.all((points >= lo - reach) & (points <= hi + reach), axis=1)
    return points[keep]


def hull_equations(points: np.ndarray) -> np.ndarray:
    """[F, 4] outward facet planes of the Quickhull convex hull: inside iff n.x + d <= 0 for all."""
    try:
        return ConvexHull(points).equations
    except QhullError as exc:
        raise BadInputError(f"cannot build the infill: surface means span no volume ({exc})") from exc


def candidate_cells(covered: np.ndarray, origin: np.ndarray, h: float, planes: np.ndarray) -> np.ndarray:
    """[K, 3] cells of this level not covered by a coarser one whose centre lies inside the hull.

    The hull is convex, so along each z column the inside is one interval: intersect the column
    with every facet's half-space (cost R^2 x facets, not R^3 x facets).
    """
    res = covered.shape[0]
    gx, gy = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    columns = np.stack([gx.ravel(), gy.ravel()], axis=1)  # [R*R, 2]
    normals, offsets = planes[:, :3], planes[:, 3]  # inside: n.x + d <= 0
    found = []
    chunk = max(1, 2_000_000 // max(1, len(planes)))
    for start in range(0, len(columns), chunk):
        col = columns[start : start + chunk]
        x = origin[0] + (col[:, 0] + 0.5) * h
        y = origin[1] + (col[:, 1] + 0.5) * h
        rhs = -(offsets + np.outer(x, normals[:, 0]) + np.outer(y, normals[:, 1]))  # [B, F]: n_z z <= rhs
        nz = normals[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = rhs / nz
        upper = np.where(nz > 1e-12, bound, np.inf).min(axis=1)
        lower = np.where(nz < -1e-12, bound, -np.inf).max(axis=1)
        flat = np.abs(nz) <= 1e-12
        blocked = (flat & (rhs < -1e-12)).any(axis=1)
        z = origin[2] + (np.arange(res) + 0.5) * h  # [R]
        inside = (z[None] >= lower[:, None] - 1e-12) & (z[None] <= upper[:, None] + 1e-12) & ~blocked[:, None]
        inside &= ~covered[col[:, 0], col[:, 1]]  # [B, R]
        b, k = np.nonzero(inside)
        found.append(np.stack([col[b, 0], col[b, 1], k], axis=1))
    return np.concatenate(found) if found else np.zeros((0, 3), dtype=np.int64)


def surface_depths(surface: dict[str, torch.Tensor], cameras: list[Camera], surface_alpha: float) -> list[torch.Tensor]:
    """Per camera, the depth [H, W] where the surface starts: where its own accumulated alpha reaches
    `surface_alpha`, or half the pixel's surface alpha where that is less.

    A still half-transparent surface keeps the noise behind most of its weight, which is the noise's job
    to make opaque. At 1/255 it is the paper's first surface Gaussian. Computed once per build: every
    infill level is pruned against the same surface."""
    args = tuple(surface[key].detach() for key in ("means", "quats", "scales", "opacities"))
    depths = []
    for cam in cameras:
        _, alpha, _ = rasterization(*args, torch.zeros_like(args[0]), cam.viewmat[None], cam.K[None], cam.width,
                                    cam.height)
        level = torch.clamp(0.5 * alpha[0, ..., 0], max=surface_alpha)
        depths.append(median_depth(*args, cam.viewmat, cam.K, cam.width, cam.height, alpha_level=level))
    return depths


def depth_prune_mask(noise: dict[str, torch.Tensor], cameras: list[Camera], depths: list[torch.Tensor]) -> torch.Tensor:
    """[M] bool: noise some view sees in front of the surface (`surface_depths` for these cameras), or where
    there is no surface."""
    marked = torch.zeros(noise["means"].shape[0], dtype=torch.bool, device=noise["means"].device)
    for cam, surface_z in zip(cameras, depths):
        marked |= seen_in_front(noise["means"], noise["quats"], noise["scales"], noise["opacities"], cam.viewmat,
                                cam.K, cam.width, cam.height, surface_z)
    return marked


def build_infill(surface: dict[str, torch.Tensor], cameras: list[Camera], cfg: InfillConfig) -> Infill:
    """surface: activated means [N,3], quats [N,4], scales [N,3], opacities [N]; full-res cameras."""
    if len(cfg.levels) != len(cfg.erosion_iters) or not cfg.levels:
        raise BadInputError(f"infill levels {cfg.levels} and erosion iterations {cfg.erosion_iters} must pair up")
    for coarse, fine in zip(cfg.levels, cfg.levels[1:]):
        if fine % coarse:
            raise BadInputError(f"infill level {fine} is not a multiple of {coarse}: levels must nest")
    device = surface["means"].device
    points = core_points(surface["means"].detach().double().cpu().numpy())
    planes = hull_equations(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = cfg.pad * (hi - lo)
    side = float(((hi + pad) - (lo - pad)).max())
    origin = (lo + hi) / 2 - side / 2
    ds = cfg.prune_downscale
    small = []
    for cam in cameras:
        K = cam.K.clone()
        K[:2] /= ds
        small.append(Camera(cam.viewmat, K, max(1, cam.width // ds), max(1, cam.height // ds)))
    occupied = np.zeros((1, 1, 1), dtype=bool)
    parts: list[Infill] = []
    depths: list[torch.Tensor] | None = None  # rendered when the first level needs them
    for index, (res, iters) in enumerate(zip(cfg.levels, cfg.erosion_iters)):
        h = side / res
        covered = occupied
        for axis in range(3):
            covered = np.repeat(covered, res // occupied.shape[0], axis=axis)
        cells = candidate_cells(covered, origin, h, planes)  # [K, 3]
        centres = origin + (cells + 0.5) * h
        level = Infill(
            torch.as_tensor(centres, dtype=torch.float32, device=device),
            torch.full((len(cells),), 0.5 * h, dtype=torch.float32, device=device),
            torch.full((len(cells),), res, dtype=torch.long, device=device),
        )
        if cfg.depth_prune and len(level):
            opacity = cfg.first_opacity if index == 0 else cfg.finer_opacity
            depths = surface_depths(surface, small, cfg.surface_alpha) if depths is None else depths
            keep = ~depth_prune_mask(level.gaussians(opacity), small, depths)
            level, cells = level.select(keep), cells[keep.cpu().numpy()]
        grid = covered.copy()
        grid[tuple(cells.T)] = True
        if cfg.erosion and iters > 0 and len(level):  # scipy reads iterations=0 as "until stable"
            eroded = binary_erosion(grid, structure=np.ones((3, 3, 3), bool), iterations=iters, border_value=0)
            keep_np = eroded[tuple(cells.T)]
            level, cells = level.select(torch.from_numpy(keep_np).to(device)), cells[keep_np]
            grid = covered.copy()
            grid[tuple(cells.T)] = True
        occupied = grid
        parts.append(level)
    return Infill(
        torch.cat([p.means for p in parts]).reshape(-1, 3),
        torch.cat([p.scales for p in parts]),
        torch.cat([p.levels for p in parts]),
    )
