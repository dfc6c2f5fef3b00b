"""Masks cut again with the stone's silhouette as the other rings predict it (station/process/cross_view.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from test_masks import iou, synthetic_pair

from sim.rig import make_stone
from sim.scene import World, render
from sim.stone import procedural_stone
from sim.truth import mask_path_for, true_masks_at
from station.cli_scan import run_sim_scan
from station.errors import BadInputError
from station.process.cross_view import CrossViewSettings, Hull, carve_hull, project_hull, roofed_part
from station.process.develop_stage import ProcessSettings
from station.process.images_io import read_mask_png
from station.process.masks import compute_mask
from station.formats.transforms import PinholeCamera
from station.process.stage import process_scan
from station.process.visual_hull import _carve, carve_grid, grid_points, view_bounds
from station.rig_geometry import RigGeometry, camera_to_turntable
from station.scanfolder import ScanFolder

RIG = RigGeometry()
INTRINSICS = PinholeCamera(RIG.width, RIG.height, RIG.focal_px, RIG.focal_px, RIG.width / 2, RIG.height / 2)


@pytest.fixture(scope="module")
def rings() -> dict[float, list[tuple[np.ndarray, np.ndarray]]]:
    """(camera-to-world, true mask) for 24 views on each of three rings of a simulated stone."""
    world = World(procedural_stone(5, look="grey"), RIG)
    return {
        elevation: [(camera_to_turntable(elevation, a, RIG), render(world, elevation, a, supersample=2).mask)
                    for a in np.arange(0.0, 360.0, 15.0)]
        for elevation in (10.0, 40.0, 70.0)
    }


def test_the_other_rings_hull_projects_onto_a_views_own_silhouette(rings) -> None:
    views = rings[10.0] + rings[70.0]
    hull = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings())
    for c2w, truth in rings[40.0][::6]:
        assert iou(project_hull(hull, c2w, INTRINSICS), truth) >= 0.94  # a hull from 48 views: about a pixel out


def test_a_hulls_silhouette_is_the_pixels_its_voxels_corner_points_land_in_with_the_holes_filled() -> None:
    rng = np.random.default_rng(1)
    hull = Hull(rng.normal(0.0, 0.02, (400, 3)), np.full(3, 0.004))
    c2w = camera_to_turntable(30.0, 20.0, RIG)
    w2c = np.linalg.inv(c2w)
    corners = np.stack(np.meshgrid(*[[-0.25, 0.25]] * 3, indexing="ij"), -1).reshape(-1, 3) * hull.voxel
    cam = (hull.surface[:, None] + corners).reshape(-1, 3) @ w2c[:3, :3].T + w2c[:3, 3]
    uvw = cam @ INTRINSICS.matrix().T
    u, v = np.floor(uvw[:, 0] / uvw[:, 2]).astype(int), np.floor(uvw[:, 1] / uvw[:, 2]).astype(int)
    assert (cam[:, 2] > 0).all() and u.min() >= 0 and v.min() >= 0 and u.max() < RIG.width and v.max() < RIG.height
    drawn = np.zeros((INTRINSICS.height, INTRINSICS.width), dtype=bool)
    drawn[v, u] = True
    silhouette = project_hull(hull, c2w, INTRINSICS)
    assert (silhouette & ~drawn).any()  # scattered points leave holes to fill ...
    np.testing.assert_array_equal(silhouette, ndimage.binary_fill_holes(drawn))  # ... and nothing else is added
    behind = Hull(hull.surface - 3.0 * c2w[:3, 2], hull.voxel)  # moved back along the optical axis, behind the camera
    assert not project_hull(behind, c2w, INTRINSICS).any()


def test_the_hull_stops_at_the_plate(rings) -> None:
    # seen only from above, the space under the stone down to the plate and beyond is never carved
    views = rings[40.0] + rings[70.0]
    hull = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings())
    assert hull.surface[:, 2].min() >= -0.5 * hull.voxel[2]
    deep = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings(plate_z=None))
    assert deep.surface[:, 2].min() < -0.005


def test_the_hull_below_its_untrusted_floor_is_left_out_of_the_silhouette(rings) -> None:
    # seen only from above, the hull is a skirt down to the plate under the stone; from the lowest ring that
    # skirt is false stone, so its lowest part is left out, and what that takes from the stone is little and low
    views = rings[40.0] + rings[70.0]
    hull = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings())
    trusted = hull.above(CrossViewSettings().untrusted_floor)
    for c2w, truth in rings[10.0][::4]:
        whole, part = project_hull(hull, c2w, INTRINSICS), project_hull(trusted, c2w, INTRINSICS)
        assert (part & ~truth).sum() < 0.85 * (whole & ~truth).sum()
        missed = truth & ~part
        assert missed.sum() <= 0.02 * truth.sum()
        rows = np.nonzero(truth.any(axis=1))[0]
        assert not missed[: rows.min() + (rows.max() - rows.min()) // 3].any()  # nothing in the stone's top third


def test_a_tolerant_hull_keeps_what_a_few_masks_lost(rings) -> None:
    # a strict hull is only as good as its worst mask: two masks that lost the stone carve it away for all
    views = rings[40.0] + rings[70.0]
    c2ws, masks = [c for c, _ in views], [m for _, m in views]
    masks[3] = masks[30] = np.zeros_like(masks[0])
    assert len(carve_hull(c2ws, masks, INTRINSICS, CrossViewSettings()).surface) == 0
    tolerant = carve_hull(c2ws, masks, INTRINSICS, CrossViewSettings(), missing_views=0.05)  # 2 of 48
    for c2w, truth in rings[40.0][::6]:
        assert iou(project_hull(tolerant, c2w, INTRINSICS), truth) >= 0.9


def test_the_carve_keeps_a_voxel_that_no_more_than_max_misses_of_the_views_seeing_it_call_background(rings) -> None:
    views = [view for ring in rings.values() for view in ring]
    c2ws, masks = [c2w for c2w, _ in views], [mask.copy() for _, mask in views]
    masks[3][:, : RIG.width // 2 - 7] = False  # one view loses most of the stone's left half
    grid = grid_points(*view_bounds(c2ws, INTRINSICS), 40)
    for max_misses in (0, 2):
        seen, misses = np.zeros(len(grid), int), np.zeros(len(grid), int)
        for c2w, mask in zip(c2ws, masks):  # the rule, voxel by voxel in plain numpy
            cam = (grid - c2w[:3, 3]) @ c2w[:3, :3]
            uvw = cam @ INTRINSICS.matrix().T
            u, v = np.floor(uvw[:, 0] / uvw[:, 2]).astype(int), np.floor(uvw[:, 1] / uvw[:, 2]).astype(int)
            sees = (cam[:, 2] > 1e-6) & (u >= 0) & (u < RIG.width) & (v >= 0) & (v < RIG.height)
            seen += sees
            misses[sees] += ~mask[v[sees], u[sees]]
        expected = (misses <= max_misses) & (seen >= len(views) // 2)
        inside, _ = carve_grid(c2ws, masks, INTRINSICS, grid, max_misses=max_misses)
        assert expected.sum() > 50
        assert (inside != expected).sum() <= 2, max_misses  # float32 and float64 may part at a pixel's edge


def test_carving_with_and_without_colour_runs_one_compiled_kernel(rings) -> None:
    """The cross-view hull carves without colour and the posing hull with it, from poses of either float width:
    one compile serves them all."""
    c2ws, masks = [c2w for c2w, _ in rings[40.0][:4]], [mask for _, mask in rings[40.0][:4]]
    images = [np.zeros((*mask.shape, 3), np.uint8) for mask in masks]
    grid = grid_points(*view_bounds(c2ws, INTRINSICS), 8)
    carve_grid([c2w.astype(np.float32) for c2w in c2ws], masks, INTRINSICS, grid)
    carve_grid(c2ws, masks, INTRINSICS, grid, images)
    assert len(_carve.signatures) == 1, _carve.signatures


def test_a_hull_above_a_share_of_its_height_drops_the_surface_below_it() -> None:
    hull = Hull(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.01]]), np.full(3, 0.001))
    assert hull.above(0.1).surface.tolist() == [[0.0, 0.0, 0.01]]
    assert hull.above(0.0) is hull  # nothing to leave out
    empty = Hull(np.zeros((0, 3)), np.zeros(3))
    assert empty.above(0.1) is empty


def test_masks_that_agree_on_nothing_give_an_empty_hull() -> None:
    c2ws = [camera_to_turntable(30.0, a, RIG) for a in (0.0, 90.0, 180.0)]
    empty = [np.zeros((RIG.height, RIG.width), dtype=bool)] * 3
    hull = carve_hull(c2ws, empty, INTRINSICS, CrossViewSettings())
    assert len(hull.surface) == 0
    assert not project_hull(hull, c2ws[0], INTRINSICS).any()


def test_a_predicted_silhouette_recovers_a_shaded_side_the_shot_alone_loses() -> None:
    # the shaded lower half is smooth, grey and darker than the plate: alone, the cut gives it to the shadow
    shot, plate, truth = synthetic_pair("pale", shading=0.15)
    assert iou(compute_mask(shot, plate), truth) < 0.9
    predicted = np.roll(truth, 1, axis=1)  # the other rings' hull is about a pixel out
    assert iou(compute_mask(shot, plate, silhouette=predicted), truth) >= 0.98


def test_only_the_edges_that_face_up_more_steeply_than_the_hulls_views_see_edge_on_may_be_roof(rings) -> None:
    # seen from 10 degrees, a hull carved from 40 and 70 degrees is untested where the stone faces up by more
    # than 50 degrees: its silhouette's top; its sides and bottom are edges the views above saw edge-on
    views = rings[40.0] + rings[70.0]
    hull = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings())
    for c2w, _ in rings[10.0][::6]:
        silhouette = project_hull(hull, c2w, INTRINSICS)
        roofed = roofed_part(silhouette, c2w, np.radians(40.0))
        rows, columns = np.nonzero(silhouette)
        top, bottom, left, right = rows.min(), rows.max(), columns.min(), columns.max()
        assert roofed[top].any() and 0.02 < roofed.sum() / silhouette.sum() < 0.5
        assert np.nonzero(roofed)[0].max() < top + 0.75 * (bottom - top)  # the lowest quarter keeps its full prior
        assert not roofed[bottom].any() and not roofed[:, left].any() and not roofed[:, right].any()
        assert not roofed_part(silhouette, c2w, np.radians(10.0)).any()  # a hull from views as low as this one
    views = rings[10.0] + rings[70.0]
    hull = carve_hull([c for c, _ in views], [m for _, m in views], INTRINSICS, CrossViewSettings())
    for c2w, _ in rings[40.0][::6]:
        assert not roofed_part(project_hull(hull, c2w, INTRINSICS), c2w, np.radians(10.0)).any()


def test_the_roofed_part_of_a_silhouette_over_a_pale_stone_weighs_too_little_to_take_in_the_backdrop() -> None:
    # seen from the lowest ring, the other rings' hull roofs a flat-topped stone: its silhouette reaches a few
    # rows above the stone, over backdrop as pale as the stone; roofed_part marks the top of such a silhouette
    shot, plate, truth = synthetic_pair("pale", shading=0.15)
    rows = np.nonzero(truth)[0]
    upper_half = np.arange(truth.shape[0])[:, None] < (rows.min() + rows.max()) // 2
    silhouette = truth.copy()
    for lift in range(1, 7):
        silhouette |= np.roll(truth, -lift, axis=0) & upper_half
    roof = silhouette & ~truth
    roofed = silhouette & (np.arange(truth.shape[0])[:, None] < rows.min() + 12)
    mask = compute_mask(shot, plate, silhouette=silhouette, roofed=roofed)
    assert (mask & roof & roofed).sum() <= 0.05 * (roof & roofed).sum()
    assert iou(mask, truth) >= 0.98
    trusting_the_roof = compute_mask(shot, plate, silhouette=silhouette)  # the full prior everywhere
    assert (trusting_the_roof & roof & roofed).sum() >= 0.5 * (roof & roofed).sum()  # measured: 495 of 526, and 0


def test_a_silhouette_or_roofed_part_of_the_wrong_size_is_refused() -> None:
    shot, plate, truth = synthetic_pair("dark")
    with pytest.raises(BadInputError, match="silhouette"):
        compute_mask(shot, plate, silhouette=truth[:-1])
    with pytest.raises(BadInputError, match="roofed part"):
        compute_mask(shot, plate, silhouette=truth, roofed=truth[:, :-1])


@pytest.mark.slow
@pytest.mark.parametrize(("sensor", "training_width"), [((320, 240), None), ((640, 480), 320)])
def test_process_cuts_a_pale_stones_lowest_rings_again_from_the_rings_above(
    tmp_path: Path, sensor: tuple[int, int], training_width: int | None
) -> None:
    # seen from the lowest ring, this stone's shaded side fades into its contact shadow (first cut: IoU 0.89
    # at 320x240); on a finer camera the re-cut runs there too and is averaged down like the first cut
    run_sim_scan(tmp_path, "pale:3", 6, 12, sensor, 0.01, lambda done, total, what: None)
    result = process_scan(tmp_path, ProcessSettings(training_width=training_width))

    scan = ScanFolder(tmp_path)
    shots = [frame for frame in result["develop"]["frames"] if frame["kind"] == "shot"]
    files = [frame["file"] for frame in shots]
    truth = (true_masks_at(tmp_path, make_stone("pale:3"), training_width, files) if training_width
             else {file: read_mask_png(mask_path_for(tmp_path, file)) for file in files})
    by_ring: dict[float, list[float]] = {}
    for frame in shots:
        mask = read_mask_png(scan.masks_dir / f"{Path(frame['file']).stem}.png")
        by_ring.setdefault(frame["elevation_deg"], []).append(iou(mask, truth[frame["file"]]))
    lowest, *above = sorted(by_ring)
    assert np.mean(by_ring[lowest]) >= 0.95
    assert all(np.mean(by_ring[e]) >= 0.98 for e in above)
    recut = {ring["elevation_deg"]: ring["recut"] for ring in result["masks_across_rings"]["rings"]}
    assert len(recut[lowest]) >= 6  # most of the lowest ring lost its shaded side
    assert all(not recut[e] for e in above[1:])  # views the shot alone masks well are left as cut
    assert (scan.images_linear_dir / "plate_e0.exr").is_file()  # the plates a re-cut needs are kept
