"""The watertight mesh: the splat's opacity level set, or TSDF fusion of depth, plus an eroded-interior
occupancy, tested against the true mesh (volume error, Chamfer-L1 with point-to-mesh distances, F-score)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from station.errors import BadInputError
from station.export.geometry_metrics import compare_meshes, fraction_outside_visual_hull
from station.export.mesh import (
    MeshConfig,
    VoxelGrid,
    build_watertight_mesh,
    check_mesh,
    opacity_mesh,
    render_depth_maps,
    resample_to_grid,
    tsdf_fuse,
    vertex_colors_from_splats,
    write_mesh_files,
)
from station.export.opacity_field import LOWPASS_VOXELS
from station.export.splat_model import SplatModel, matrix_to_quat
from station.rig_geometry import look_at_c2w

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STONES = sorted((DATA / "meshes").glob("*.ply")) if (DATA / "meshes").is_dir() else []


def stone_on_plate(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The stone as the turntable holds it: centred on the axis, resting on z = 0."""
    mesh = mesh.copy()
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def hemisphere_cameras(mesh: trimesh.Trimesh, width: int, height: int, n_azimuth: int = 16):
    """Upper-hemisphere views framing the stone, as the rig's elevation rings do. (Ks, c2ws)"""
    radius = 2.5 * float(np.linalg.norm(mesh.extents))
    target = np.array([0.0, 0.0, mesh.extents[2] / 2])
    focal = 0.5 * width / np.tan(np.radians(14))
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    c2ws = []
    for elevation in (5.0, 25.0, 45.0, 65.0, 85.0):
        for azimuth in np.arange(n_azimuth) * 360.0 / n_azimuth + elevation:
            e, a = np.radians(elevation), np.radians(azimuth)
            eye = target + radius * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            c2ws.append(look_at_c2w(eye, target))
    return np.repeat(K[None], len(c2ws), 0), np.array(c2ws)


def raycast_depths(mesh: trimesh.Trimesh, Ks: np.ndarray, c2ws: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera z-depth of the first hit per pixel centre, +inf where the ray misses. [V, H, W]"""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    depths = []
    for K, c2w in zip(Ks, c2ws):
        rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        dirs = rays_cam @ c2w[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origins = np.repeat(c2w[None, :3, 3], len(dirs), 0)
        hits, ray_idx, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
        depth = np.full(len(dirs), np.inf)
        depth[ray_idx] = (hits - c2w[:3, 3]) @ c2w[:3, 2]
        depths.append(depth.reshape(height, width))
    return np.array(depths, np.float32)


def eroded_occupancy(mesh: trimesh.Trimesh, grid: VoxelGrid, erode_voxels: int = 1) -> np.ndarray:
    """Stand-in for the NGS infill: the true interior, shrunk as an infill sits inside the surface."""
    inside = mesh.contains(grid.centres()).reshape(grid.shape)
    return ndimage.binary_erosion(inside, iterations=erode_voxels).astype(np.float32)


def reconstruct(mesh: trimesh.Trimesh, resolution: int = 96, size: tuple[int, int] = (96, 72), n_azimuth: int = 8):
    truth = stone_on_plate(mesh)
    voxel = float(truth.extents.max()) / resolution
    grid = VoxelGrid.around(truth.bounds[0], truth.bounds[1], voxel)
    Ks, c2ws = hemisphere_cameras(truth, *size, n_azimuth=n_azimuth)
    depths = raycast_depths(truth, Ks, c2ws, *size)
    occupancy = eroded_occupancy(truth, grid)
    return truth, build_watertight_mesh(depths, Ks, c2ws, occupancy, grid, MeshConfig(target_faces=20_000))


def bumpy_stone() -> trimesh.Trimesh:
    """A procedural stone: a flattened, bumpy icosphere about 8 cm across (metres)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.04)
    v = sphere.vertices
    bump = 1 + 0.08 * np.sin(5 * v[:, 0] / 0.04) * np.cos(4 * v[:, 1] / 0.04) + 0.05 * np.sin(7 * v[:, 2] / 0.04)
    return trimesh.Trimesh(v * bump[:, None] * np.array([1.0, 0.8, 0.6]), sphere.faces)


def test_fusion_marks_free_space_outside_and_behind_surface_inside():
    grid = VoxelGrid((-0.05, -0.05, 0.0), 0.01, (11, 11, 11))
    K = np.array([[50.0, 0, 8], [0, 50.0, 8], [0, 0, 1]])
    c2w = look_at_c2w(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    depth = np.full((1, 16, 16), 0.95, np.float32)  # a wall at z = 0.05
    tsdf, weight = tsdf_fuse(depth, K[None], c2w[None], grid, truncation=0.03)
    assert tsdf[5, 5, 10] == pytest.approx(1.0)  # z = 0.10: in front, free
    assert tsdf[5, 5, 5] == pytest.approx(0.0, abs=1e-4)  # on the wall
    assert tsdf[5, 5, 3] == pytest.approx(-2 / 3, abs=1e-4)  # 2 cm behind it
    assert weight[5, 5, 0] == 0  # 5 cm behind: never observed


def test_fused_bumpy_stone_is_closed_one_body_and_accurate():
    truth, mesh = reconstruct(bumpy_stone(), resolution=80, size=(80, 60))
    check = check_mesh(mesh)
    assert check.ok, check.problems()
    errors = compare_meshes(mesh, truth, samples=4000)
    assert abs(errors.volume_rel_error) <= 0.02
    assert errors.chamfer_fraction_of_diagonal <= 0.005
    assert errors.fscore >= 0.9


@pytest.mark.shared_data
@pytest.mark.slow
@pytest.mark.skipif(not STONES, reason="real stone meshes absent from ../shared/data/meshes")
@pytest.mark.parametrize("path", STONES, ids=[p.stem for p in STONES])
def test_real_stone_meets_volume_and_chamfer_targets(path: Path):
    truth, mesh = reconstruct(trimesh.load_mesh(path))
    check = check_mesh(mesh)
    assert check.ok, check.problems()
    errors = compare_meshes(mesh, truth, samples=4000)
    assert abs(errors.volume_rel_error) <= 0.02, errors
    assert errors.chamfer_fraction_of_diagonal <= 0.005, errors


def surface_splat(mesh: trimesh.Trimesh, n: int, flatness: float = 0.1, width: float = 0.5) -> SplatModel:
    """Opaque flat discs tangent to the surface (`flatness`: thickness over width; `width`: disc sigma over
    the sample spacing), a stand-in for a trained NGS surface splat."""
    points, face = trimesh.sample.sample_surface_even(mesh, n, seed=0)
    quats = []
    for normal in mesh.face_normals[face]:
        x = np.cross(normal, [0.3, 0.5, 0.8])
        x /= np.linalg.norm(x)
        quats.append(matrix_to_quat(np.stack([x, np.cross(normal, x), normal], 1)))
    sigma = width * np.sqrt(mesh.area / len(points))
    return SplatModel(
        points, np.log(np.tile([sigma, sigma, flatness * sigma], (len(points), 1))), np.array(quats),
        np.full(len(points), 5.0), np.zeros((len(points), 3)), np.zeros((len(points), 0, 3)),
    )


@pytest.mark.slow
def test_rendered_splat_depth_fuses_to_the_stone():
    truth = stone_on_plate(bumpy_stone())
    grid = VoxelGrid.around(truth.bounds[0], truth.bounds[1], float(truth.extents.max()) / 64)
    Ks, c2ws = hemisphere_cameras(truth, 80, 60, n_azimuth=4)
    depths = render_depth_maps(surface_splat(truth, 8000), c2ws, Ks, 80, 60, MeshConfig())
    assert np.isposinf(depths).mean() > 0.5  # background seen as free space
    mesh = build_watertight_mesh(depths, Ks, c2ws, eroded_occupancy(truth, grid), grid)
    assert check_mesh(mesh).ok
    errors = compare_meshes(mesh, truth, samples=3000)
    # Looser than for ray-cast depth: splat depth blends Gaussian-centre depths (biased towards
    # the camera by about a disc's size) and this crude disc splat is not trained.
    assert abs(errors.volume_rel_error) <= 0.03, errors
    assert errors.chamfer_fraction_of_diagonal <= 0.01, errors


def gaussians(means, scales, quats, opacity: float) -> SplatModel:
    n = len(means)
    return SplatModel(np.asarray(means), np.log(np.asarray(scales)), np.asarray(quats),
                      np.full(n, np.log(opacity / (1 - opacity))), np.zeros((n, 3)), np.zeros((n, 0, 3)))


def test_one_gaussian_meshes_to_the_ellipsoid_where_its_opacity_is_one_half():
    scales = np.array([0.02, 0.012, 0.007])
    model = gaussians([[0.01, -0.02, 0.05]], [scales], [matrix_to_quat(look_at_c2w(np.ones(3), np.zeros(3))[:3, :3])],
                      0.99)
    grid = VoxelGrid.around(np.array([-0.06, -0.08, 0.0]), np.array([0.08, 0.04, 0.1]), 0.001)
    mesh = opacity_mesh(model, np.zeros(grid.shape, np.float32), grid)
    widened = np.sqrt(scales**2 + (LOWPASS_VOXELS * grid.voxel_size) ** 2)  # the grid's low-pass
    semi_axes = widened * np.sqrt(2 * np.log(2 * 0.99))  # 0.99 exp(-r^2/2) = 1/2
    assert check_mesh(mesh).ok
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * np.prod(semi_axes), rel=0.02)
    assert mesh.centroid == pytest.approx([0.01, -0.02, 0.05], abs=grid.voxel_size / 4)


def test_a_dome_of_gaussians_on_the_plate_is_meshed_solid_without_an_infill():
    """The hollow under a dome is closed by the plate, as the unseen bottom of a stone is: it is inside,
    so the mesh is the half ball, not a skin."""
    n, radius = 4000, 0.03
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    points = radius * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    points = points[points[:, 2] >= 0]
    spacing = radius * np.sqrt(4 * np.pi / n)
    model = gaussians(points, np.full((len(points), 3), 0.6 * spacing), np.tile([1.0, 0, 0, 0], (len(points), 1)), 0.9)
    grid = VoxelGrid.around(np.array([-0.04, -0.04, 0.0]), np.array([0.04, 0.04, 0.04]), 0.001)
    mesh = opacity_mesh(model, np.zeros(grid.shape, np.float32), grid)
    assert check_mesh(mesh).ok and mesh.body_count == 1
    assert mesh.volume > 0.95 * 2 / 3 * np.pi * radius**3


def test_a_see_through_splat_has_no_surface_to_mesh_even_with_an_infill():
    truth = stone_on_plate(bumpy_stone())
    grid = VoxelGrid.around(truth.bounds[0], truth.bounds[1], float(truth.extents.max()) / 32)
    faint = surface_splat(truth, 2000)
    faint.opacity_logit[:] = -5.0  # opacity 0.007
    with pytest.raises(BadInputError, match="nowhere opaque"):
        opacity_mesh(faint, eroded_occupancy(truth, grid), grid)


def test_written_files_reload_watertight_in_their_own_frames(tmp_path: Path):
    truth, mesh = reconstruct(bumpy_stone(), resolution=48, size=(64, 48))
    rng = np.random.default_rng(0)
    n = 300
    model = SplatModel(
        truth.sample(n, seed=1), np.full((n, 3), -6.0), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 3.0),
        rng.normal(size=(n, 3)), np.zeros((n, 0, 3)),
    )
    colors = vertex_colors_from_splats(mesh.vertices, model)
    checks = write_mesh_files(mesh, tmp_path / "mesh.ply", tmp_path / "mesh.glb", tmp_path / "mesh.stl", colors)
    assert len(checks) == 3
    for path, check in checks.items():
        assert check.ok, (path, check.problems())
        assert check.volume_m3 == pytest.approx(mesh.volume, rel=1e-4)
    glb = trimesh.load_mesh(tmp_path / "mesh.glb")
    assert glb.extents[1] == pytest.approx(mesh.extents[2], rel=1e-5)  # glTF: stone's up is +Y
    ply = trimesh.load_mesh(tmp_path / "mesh.ply")
    assert ply.visual.vertex_colors.shape == (len(ply.vertices), 4)


def test_broken_meshes_are_reported_with_their_problems():
    open_box = trimesh.creation.box()
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    assert "mesh has holes (not watertight)" in check_mesh(open_box).problems()
    two = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([3, 0, 0])])
    assert any("2 separate bodies" in p for p in check_mesh(two).problems())
    inverted = trimesh.creation.box()
    inverted.invert()
    assert any("not positive" in p for p in check_mesh(inverted).problems())


def test_occupancy_resamples_onto_the_mesh_grid_and_is_empty_outside_its_source():
    source = VoxelGrid((0.0, 0.0, 0.0), 0.01, (10, 10, 10))
    values = np.zeros(source.shape, np.float32)
    values[:5] = 1.0  # x <= 0.04 occupied
    target = VoxelGrid((0.005, 0.0, 0.0), 0.01, (12, 10, 10))
    out = resample_to_grid(values, source, target)
    assert out[3, 5, 5] == pytest.approx(1.0)  # x = 0.035
    assert out[4, 5, 5] == pytest.approx(0.5)  # x = 0.045, half-way across the boundary
    assert out[11, 5, 5] == 0.0  # x = 0.115, beyond the source grid


def test_empty_field_is_refused_with_a_typed_error():
    grid = VoxelGrid((0.0, 0.0, 0.0), 0.01, (8, 8, 8))
    with pytest.raises(BadInputError, match="no surface"):
        build_watertight_mesh(
            np.full((1, 8, 8), np.inf, np.float32), np.eye(3)[None], np.eye(4)[None], np.zeros(grid.shape), grid
        )


def test_visual_hull_counts_gaussians_that_a_mask_rejects():
    K = np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]])
    c2w = look_at_c2w(np.array([0.0, 0.0, 1.0]), np.zeros(3), up=np.array([0.0, 1.0, 0.0]))
    mask = np.zeros((1, 10, 10), bool)
    mask[0, 3:7, 3:7] = True
    means = np.array([[0.0, 0.0, 0.0], [0.4, 0.4, 0.0], [0.01, -0.01, 0.0], [5.0, 5.0, 0.0]])
    # the last centre projects outside the frame: not judged, so 1 of 4 is outside
    assert fraction_outside_visual_hull(means, mask, K[None], c2w[None]) == pytest.approx(0.25)


def test_visual_hull_tolerance_forgives_centres_on_the_mask_edge_but_not_floaters():
    K = np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]])
    c2w = look_at_c2w(np.array([0.0, 0.0, 1.0]), np.zeros(3), up=np.array([0.0, 1.0, 0.0]))
    mask = np.zeros((1, 10, 10), bool)
    mask[0, 3:7, 3:7] = True
    edge = [0.25, 0.0, 0.0]  # projects to column 7, one pixel past the mask
    floater = [-0.45, -0.45, 0.0]  # projects to (0, 0), far from the stone
    means = np.array([[0.0, 0.0, 0.0], edge, floater])
    assert fraction_outside_visual_hull(means, mask, K[None], c2w[None]) == pytest.approx(2 / 3)
    assert fraction_outside_visual_hull(means, mask, K[None], c2w[None], tolerance_px=1) == pytest.approx(1 / 3)
