"""A watertight, metric, one-body mesh of the stone from its splats.

The surface is the 0.5 level set of the splat's own opacity field (station.export.opacity_field):
where the Gaussians, as the rasteriser composites them, turn opaque. The alternative (`surface =
"tsdf"`) fuses rendered median-depth maps into a TSDF; it reports Gaussian centres, which lie about
one Gaussian scale inside the visible boundary, so its meshes come out small (bench/mesh.py).
Neither closes the stone alone: the turntable sees the upper hemisphere only and never the bottom.
So the NGS infill occupancy fills whatever the surface leaves open inside (a TSDF knows only a band
around the seen surface), the turntable plane z=0 is a cut (the stone sits on the plate: below it
is outside, and the footprint is closed by the cut), and the grid border is outside. Marching
cubes of that field is closed by construction; the largest component is kept, lightly smoothed
and decimated. Fusion is a pure numpy function of depth maps so it can be tested against
ray-cast ground truth without the rasteriser.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import fast_simplification
import manifold3d
import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage import measure

from station.errors import BadInputError
from station.export.opacity_field import opacity_field
from station.export.splat_model import TURNTABLE_TO_YUP, SplatModel
from station.scanfolder import atomic_write_bytes


@dataclass(frozen=True)
class VoxelGrid:
    """An axis-aligned voxel grid in the turntable frame; values sit at voxel centres."""

    origin: tuple[float, float, float]  # centre of voxel (0, 0, 0), metres
    voxel_size: float  # metres
    shape: tuple[int, int, int]

    @staticmethod
    def around(lo: np.ndarray, hi: np.ndarray, voxel_size: float, pad_voxels: int = 3) -> "VoxelGrid":
        """A grid covering the box [lo, hi] plus `pad_voxels` of margin on every side."""
        lo = np.asarray(lo, np.float64) - pad_voxels * voxel_size
        hi = np.asarray(hi, np.float64) + pad_voxels * voxel_size
        shape = np.ceil((hi - lo) / voxel_size).astype(int) + 1
        if np.any(shape < 4) or np.prod(shape) > 512**3:
            raise BadInputError(f"voxel grid of shape {shape.tolist()} is degenerate or too large")
        return VoxelGrid(tuple(lo.tolist()), float(voxel_size), tuple(int(s) for s in shape))

    def axes(self) -> list[np.ndarray]:
        return [self.origin[i] + self.voxel_size * np.arange(self.shape[i]) for i in range(3)]

    def centres(self) -> np.ndarray:
        """Voxel centres, [X*Y*Z, 3] in C order."""
        gx, gy, gz = np.meshgrid(*self.axes(), indexing="ij")
        return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)


SHELL_CLOSING_VOXELS = 1  # pinholes up to twice this wide in the opacity shell do not open its inside


@dataclass
class MeshConfig:
    surface: str = "opacity"  # "opacity": the splat's opacity level set; "tsdf": fused median depth maps
    truncation_voxels: float = 3.0  # TSDF band half-width, in voxels
    target_faces: int = 60_000  # decimation target; fewer faces are left alone
    taubin_iterations: int = 10  # light smoothing that keeps volume
    opaque_alpha: float = 0.5  # rendered alpha above which a pixel's depth is a surface
    empty_alpha: float = 0.05  # rendered alpha below which a pixel sees free space
    min_view_cosine: float = 0.75  # rendered depth seen more obliquely than 41 deg is not fused


def tsdf_fuse(
    depths: np.ndarray, Ks: np.ndarray, c2ws: np.ndarray, grid: VoxelGrid, truncation: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse z-depth maps into a truncated signed distance grid (positive outside, in [-1, 1]).

    depths [V, H, W]: camera z-depth of the surface, +inf where the ray sees nothing (free
    space), NaN where unknown. Ks [V, 3, 3], c2ws [V, 4, 4] OpenCV camera-to-world.
    Returns (tsdf [X, Y, Z], weight [X, Y, Z]); weight 0 marks voxels no view observed.
    """
    depths = np.asarray(depths, np.float32)
    if depths.ndim != 3 or Ks.shape != (len(depths), 3, 3) or c2ws.shape != (len(depths), 4, 4):
        raise BadInputError(f"tsdf_fuse: depths {depths.shape}, Ks {Ks.shape}, c2ws {c2ws.shape} disagree")
    _, height, width = depths.shape
    # A free-space pixel beside a surface pixel straddles the silhouette: its footprint holds
    # both, so it is unknown. Trusting it carves half a pixel off every silhouette.
    surface = np.isfinite(depths)
    straddles = ndimage.binary_dilation(surface, structure=np.ones((1, 3, 3), bool)) & np.isposinf(depths)
    depths = np.where(straddles, np.float32(np.nan), depths)
    points = grid.centres().astype(np.float32)  # [P, 3]
    tsdf = np.zeros(len(points), np.float32)
    weight = np.zeros(len(points), np.float32)
    for depth, K, c2w in zip(depths, Ks, c2ws):
        w2c = np.linalg.inv(c2w).astype(np.float32)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]  # [P, 3]
        z = cam[:, 2]
        in_front = z > 1e-6
        zs = np.where(in_front, z, 1.0)
        u = np.floor(K[0, 0] * cam[:, 0] / zs + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * cam[:, 1] / zs + K[1, 2]).astype(np.int64)
        visible = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        d = np.full(len(points), np.nan, np.float32)
        d[visible] = depth[v[visible], u[visible]]
        sdf = d - z  # [P] along the optical axis; +inf for free-space rays
        update = visible & ~np.isnan(d) & (sdf > -truncation)
        value = np.clip(sdf[update] / truncation, -1.0, 1.0)
        tsdf[update] = (tsdf[update] * weight[update] + value) / (weight[update] + 1.0)
        weight[update] += 1.0
    return tsdf.reshape(grid.shape), weight.reshape(grid.shape)


def combine_fields(
    tsdf: np.ndarray, weight: np.ndarray, occupancy: np.ndarray, grid: VoxelGrid, truncation: float
) -> np.ndarray:
    """Signed field, positive inside: TSDF where observed, infill occupancy elsewhere, plate and border outside."""
    if not (tsdf.shape == weight.shape == occupancy.shape == grid.shape):
        raise BadInputError(f"combine_fields: shapes {tsdf.shape}, {weight.shape}, {occupancy.shape} vs grid {grid.shape}")
    field = np.where(weight > 0, -tsdf, 2.0 * np.clip(occupancy, 0.0, 1.0) - 1.0).astype(np.float32)
    return close_on_plate(field, grid, truncation)


def close_on_plate(field: np.ndarray, grid: VoxelGrid, ramp: float) -> np.ndarray:
    """Cut a signed field (positive inside, in [-1, 1]) at the plate z = 0 and make the grid border outside,
    so its zero level set is closed. `ramp`: the height over which the plate's cut fades out."""
    z = grid.axes()[2]
    plate = np.clip(z / ramp, -1.0, 1.0).astype(np.float32)  # positive above the plate
    field = np.minimum(field, plate[None, None, :])
    field[[0, -1], :, :] = -1.0
    field[:, [0, -1], :] = -1.0
    field[:, :, [0, -1]] = -1.0
    return field


def opacity_mesh(model: SplatModel, occupancy: np.ndarray, grid: VoxelGrid, config: MeshConfig | None = None
                 ) -> trimesh.Trimesh:
    """The splat's opacity level set at 0.5 (station.export.opacity_field), with the infill body (on
    `grid`) filling whatever the surface leaves open, closed on the plate."""
    if occupancy.shape != grid.shape:
        raise BadInputError(f"opacity_mesh: occupancy {occupancy.shape} does not match grid {grid.shape}")
    surface = opacity_field(model, np.asarray(grid.origin), grid.voxel_size, grid.shape)
    if surface.max() < 0.5:  # the infill alone would mesh: a see-through splat must not pass as a body
        raise BadInputError(f"the splat is nowhere opaque (its opacity field peaks at {surface.max():.3f} < 0.5); "
                            "there is no surface to mesh")
    inside = np.maximum(surface, np.clip(occupancy, 0.0, 1.0))
    # A hollow left between the surface shell and the infill (or closed only by the plate, under the
    # unseen bottom) is inside the stone: nothing outside can reach it. The shell is sampled on the
    # grid, so it is thickened to close pinholes a voxel wide before asking, and the hollow found
    # inside the thickened shell is grown back out to the shell (not into the surface's own crevices).
    below = np.broadcast_to(grid.axes()[2][None, None, :] < 0.0, inside.shape)
    thick = ndimage.binary_dilation((inside >= 0.5) | below, iterations=SHELL_CLOSING_VOXELS)
    hollow = ndimage.binary_fill_holes(thick) & ~thick
    hollow = ndimage.binary_dilation(hollow, iterations=SHELL_CLOSING_VOXELS) & ~below & (inside < 0.5)
    inside[hollow] = 1.0
    field = close_on_plate((2.0 * inside - 1.0).astype(np.float32), grid, grid.voxel_size)
    return extract_mesh(field, grid, config or MeshConfig())


def resample_to_grid(values: np.ndarray, source: VoxelGrid, target: VoxelGrid) -> np.ndarray:
    """Trilinear resampling of a voxel field (e.g. the infill occupancy) onto another grid; 0 outside."""
    if values.shape != source.shape:
        raise BadInputError(f"resample_to_grid: values {values.shape} do not match grid {source.shape}")
    index = (target.centres() - np.asarray(source.origin)) / source.voxel_size  # [P, 3]
    out = ndimage.map_coordinates(values.astype(np.float32), index.T, order=1, mode="constant", cval=0.0)
    return out.reshape(target.shape)


def extract_mesh(field: np.ndarray, grid: VoxelGrid, config: MeshConfig) -> trimesh.Trimesh:
    """Marching cubes at 0, outward winding, largest body, Taubin smoothing, decimation."""
    if field.max() <= 0 or field.min() >= 0:
        raise BadInputError("extract_mesh: the fused field has no surface (all inside or all outside)")
    # A value of exactly 0 at a voxel centre (the plate plane through a layer of centres) makes
    # zero-area triangles that later merge into pinched vertices; nudge it off the level.
    field = np.where(field == 0.0, np.float32(-1e-6), field)
    verts, faces, _, _ = measure.marching_cubes(field, level=0.0, spacing=(grid.voxel_size,) * 3)
    mesh = trimesh.Trimesh(verts + np.asarray(grid.origin), faces, process=True)
    bodies = mesh.split(only_watertight=False)
    mesh = max(bodies, key=lambda b: abs(b.volume)) if len(bodies) > 1 else mesh
    if mesh.volume < 0:
        mesh.invert()
    if config.taubin_iterations:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=config.taubin_iterations)
    if len(mesh.faces) > config.target_faces:
        # Low aggressiveness: at the default (7) collapses fold thin parts into edges shared by
        # four faces, which breaks watertightness; at 2 they stay closed.
        v, f = fast_simplification.simplify(
            mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64), target_count=config.target_faces, agg=2
        )
        decimated = trimesh.Trimesh(v, f, process=True)
        if check_mesh(decimated).ok:  # quadric collapse can pinch thin parts; keep the full mesh then
            mesh = decimated
    return mesh


@dataclass
class MeshCheck:
    watertight: bool
    winding_consistent: bool
    volume_m3: float
    area_m2: float
    manifold_status: str
    bodies: int
    pinched_vertices: int
    genus: int

    @property
    def ok(self) -> bool:
        return not self.problems()

    def to_metrics(self) -> dict:
        """The keys `metrics.json` and the gate read."""
        return {
            "mesh_watertight": self.watertight and self.winding_consistent and self.volume_m3 > 0,
            "mesh_manifold": self.manifold_status == "NoError" and self.pinched_vertices == 0 and self.bodies == 1,
            "mesh_problems": self.problems(),
            "mesh_volume_m3": self.volume_m3,
            "mesh_area_m2": self.area_m2,
            "mesh_genus": self.genus,
        }

    def problems(self) -> list[str]:
        out = []
        if not self.watertight:
            out.append("mesh has holes (not watertight)")
        if not self.winding_consistent:
            out.append("face winding is inconsistent")
        if not self.volume_m3 > 0:
            out.append(f"volume {self.volume_m3:.3g} m^3 is not positive (inside-out or open)")
        if self.manifold_status != "NoError":
            out.append(f"manifold3d rejects the mesh: {self.manifold_status}")
        if self.pinched_vertices:
            out.append(f"{self.pinched_vertices} pinched (non-manifold) vertices")
        if self.bodies != 1:
            out.append(f"mesh has {self.bodies} separate bodies, expected one")
        return out


def check_mesh(mesh: trimesh.Trimesh) -> MeshCheck:
    """trimesh and manifold3d checks; manifold3d silently splits pinched vertices, so count them."""
    mesh = mesh.copy()
    mesh.remove_unreferenced_vertices()
    manifold = manifold3d.Manifold(
        manifold3d.Mesh(
            vert_properties=np.ascontiguousarray(mesh.vertices, np.float32),
            tri_verts=np.ascontiguousarray(mesh.faces, np.uint32),
        )
    )
    status = manifold.status()
    no_error = status == manifold3d.Error.NoError
    pinched = max(0, manifold.num_vert() - len(mesh.vertices)) if no_error else 0
    bodies = len(mesh.split(only_watertight=False)) if len(mesh.faces) else 0
    return MeshCheck(
        watertight=bool(mesh.is_watertight),
        winding_consistent=bool(mesh.is_winding_consistent),
        volume_m3=float(mesh.volume) if len(mesh.faces) else 0.0,
        area_m2=float(mesh.area),
        manifold_status=str(status.name) if hasattr(status, "name") else str(status),
        bodies=bodies,
        pinched_vertices=int(pinched),
        genus=int(round((2 - mesh.euler_number) / 2)) if bodies == 1 else -1,
    )


def vertex_colors_from_splats(vertices: np.ndarray, model: SplatModel, k: int = 8) -> np.ndarray:
    """RGBA uint8 per vertex: opacity- and distance-weighted colour of the nearest opaque Gaussians."""
    keep = model.opacity() > 0.5
    source = model.subset(keep) if keep.sum() >= k else model
    tree = cKDTree(source.means)
    dist, idx = tree.query(vertices, k=min(k, source.num))  # [V, k]
    dist, idx = dist.reshape(len(vertices), -1), idx.reshape(len(vertices), -1)
    w = source.opacity()[idx] / (dist + 1e-5)  # [V, k]
    rgb = np.einsum("vk,vkc->vc", w, source.rgb()[idx]) / w.sum(axis=1, keepdims=True)
    rgba = np.concatenate([rgb, np.ones((len(vertices), 1))], axis=1)
    return np.clip(np.round(rgba * 255), 0, 255).astype(np.uint8)


def render_depth_maps(
    model: SplatModel, c2ws: np.ndarray, Ks: np.ndarray, width: int, height: int, config: MeshConfig
) -> np.ndarray:
    """Depth maps [V, H, W] of the splats for `tsdf_fuse`: the median depth (where alpha reaches 0.5,
    on the first opaque layer; expected depth lies about one Gaussian scale behind it) where the pixel is opaque, +inf
    where it sees through, NaN on the soft silhouette in between."""
    import torch

    from station.ngs.raster import median_depth, rasterization

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, np.float32))

    gaussians = [t(model.means), t(model.quats), t(np.exp(model.scales_log)), t(model.opacity())]
    rgb = t(model.rgb())
    depths = []
    with torch.no_grad():
        for c2w, K in zip(c2ws, Ks):
            viewmat = t(np.linalg.inv(c2w))  # world-to-camera
            _, alpha, _ = rasterization(*gaussians, rgb, viewmat[None], t(K)[None], width, height)
            alpha = alpha[0, ..., 0].numpy()  # [H, W]
            depth = median_depth(*gaussians, viewmat, t(K), width, height).numpy()  # [H, W]
            out = np.where(alpha >= config.opaque_alpha, depth, np.nan)
            out = np.where(alpha <= config.empty_alpha, np.inf, out)
            out[grazing(out, K, config.min_view_cosine)] = np.nan
            depths.append(out)
    return np.stack(depths).astype(np.float32)


def grazing(depth: np.ndarray, K: np.ndarray, min_cosine: float) -> np.ndarray:
    """Pixels [H, W] that see the surface at a grazing angle (|cos| between ray and normal below
    `min_cosine`). Splat depth is a blend of Gaussian-centre depths, biased towards the camera by
    about a Gaussian's size times the slope; other views see those surfaces head-on."""
    height, width = depth.shape
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # [H, W, 3]
    finite = np.where(np.isfinite(depth), depth, np.nan)
    points = rays * finite[..., None]
    normal = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))  # [H, W, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.abs(np.sum(normal * rays, -1)) / (np.linalg.norm(normal, axis=-1) * np.linalg.norm(rays, axis=-1))
    return np.isfinite(depth) & ~(cosine >= min_cosine)


def build_watertight_mesh(
    depths: np.ndarray,
    Ks: np.ndarray,
    c2ws: np.ndarray,
    occupancy: np.ndarray,
    grid: VoxelGrid,
    config: MeshConfig | None = None,
) -> trimesh.Trimesh:
    """Depth maps + infill occupancy (on `grid`) to a closed mesh; see the module docstring."""
    config = config or MeshConfig()
    truncation = config.truncation_voxels * grid.voxel_size
    tsdf, weight = tsdf_fuse(depths, Ks, c2ws, grid, truncation)
    return extract_mesh(combine_fields(tsdf, weight, occupancy, grid, truncation), grid, config)


def _reload(path: Path, to_turntable: np.ndarray | None) -> trimesh.Trimesh:
    loaded = trimesh.load_mesh(path, process=True)
    if to_turntable is not None:
        loaded.apply_transform(to_turntable)
    return loaded


def write_mesh_files(
    mesh: trimesh.Trimesh,
    ply_path: Path,
    glb_path: Path,
    stl_path: Path | None = None,
    colors: np.ndarray | None = None,
) -> dict[str, MeshCheck]:
    """Write PLY (turntable frame, +Z up), GLB (+Y up, as glTF requires) and optionally STL, each
    atomically, then reload every written file and check it again: a mesh is only as good as
    what a downstream tool reads back. Returns the check of each reloaded file by path."""
    out = mesh.copy()
    if colors is not None:
        out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=colors)
    to_yup = np.eye(4)
    to_yup[:3, :3] = TURNTABLE_TO_YUP
    glb_mesh = out.copy()
    glb_mesh.apply_transform(to_yup)
    files = [(Path(ply_path), out, "ply", None), (Path(glb_path), glb_mesh, "glb", to_yup.T)]
    if stl_path is not None:
        files.append((Path(stl_path), out, "stl", None))
    checks = {}
    for path, item, kind, back in files:
        atomic_write_bytes(path, item.export(file_type=kind))
        checks[str(path)] = check_mesh(_reload(path, back))
    return checks
