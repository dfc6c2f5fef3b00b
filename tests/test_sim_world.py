"""The simulated stone world: stones, softbox render, sensor, frame source and sim_truth."""

from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import rawpy
import trimesh
from PIL import Image
from trimesh.ray import ray_pyembree

from sim.dng import read_dng
from sim.lens import SimLens
from sim.scene import CHART_LINEAR_SRGB, World, camera_rays, frame_source, render
from sim.sensor import SensorModel
from sim.stone import BACKDROP_ALBEDO, LOOKS, load_stone_mesh, procedural_stone
from sim.truth import (
    TruthFrame, TruthImage, image_path_for, mask_path_for, read_truth_image, true_images_at, write_sim_truth,
    write_truth_frame, write_truth_frames,
)
from station.errors import BadInputError, ScanFolderError
from station.rig_geometry import RigGeometry, camera_to_turntable

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="module")
def world() -> World:
    return World(procedural_stone(11, look="grey", sheen=0.2))


def _project(points: np.ndarray, elevation: float, azimuth: float, rig: RigGeometry) -> np.ndarray:
    """[N, 3] world points -> [N, 2] pixel coordinates (pixel centres at +0.5)."""
    w2c = np.linalg.inv(camera_to_turntable(elevation, azimuth, rig))
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    uv = cam @ rig.intrinsics().T
    return uv[:, :2] / uv[:, 2:]


# Stones ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("look", LOOKS)
def test_procedural_stones_are_watertight_and_rest_on_the_plate_at_the_axis(look):
    stone = procedural_stone(3, size_m=0.08, look=look)
    mesh = stone.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose((mesh.bounds[0, :2] + mesh.bounds[1, :2]) / 2, 0.0, atol=1e-12)
    assert mesh.extents.max() == pytest.approx(0.08)


def test_the_same_seed_makes_the_same_stone_and_another_seed_another():
    a, b, c = procedural_stone(5), procedural_stone(5), procedural_stone(6)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.albedo(a.mesh.vertices), b.albedo(b.mesh.vertices))
    assert not np.allclose(a.mesh.vertices, c.mesh.vertices)


def test_looks_have_the_albedo_their_names_promise():
    points = procedural_stone(2).mesh.sample(4000, seed=0)
    albedo = {look: procedural_stone(2, look=look).albedo(points) for look in LOOKS}
    assert 0.05 <= albedo["dark"].mean() <= 0.1
    assert np.abs(albedo["pale"].mean(axis=0) - BACKDROP_ALBEDO).max() < 0.03
    contrast = {look: albedo[look].mean(axis=1).std() / albedo[look].mean() for look in LOOKS}
    assert contrast["textureless"] < 0.02
    assert contrast["grey"] < 0.25  # rock-like: low contrast, not a test card
    assert contrast["patterned"] > contrast["grey"]
    shifted = points + np.array([0.01, 0.02, -0.01])  # whole periods of the 1 cm motif
    np.testing.assert_allclose(procedural_stone(2, look="patterned").albedo(shifted), albedo["patterned"], atol=1e-6)


def test_bad_stone_parameters_are_refused():
    with pytest.raises(BadInputError, match="look"):
        procedural_stone(1, look="glossy")
    with pytest.raises(BadInputError, match="size"):
        procedural_stone(1, size_m=3.0)


def test_a_file_that_is_not_a_mesh_is_refused(tmp_path):
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(BadInputError, match="junk.ply"):
        load_stone_mesh(junk)


@pytest.mark.shared_data
@pytest.mark.skipif(not (SHARED / "meshes").is_dir(), reason="shared data absent")
@pytest.mark.parametrize("name", ["stone_073ac15d_mesh.ply", "low_res_AAA.ply"])
def test_real_meshes_load_centred_on_the_axis_and_resting_on_the_plate(name):
    stone = load_stone_mesh(SHARED / "meshes" / name, look="speckled")
    mesh = stone.mesh
    assert mesh.is_watertight
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose((mesh.bounds[0, :2] + mesh.bounds[1, :2]) / 2, 0.0, atol=1e-9)
    assert 0.05 < mesh.extents.max() < 0.25  # metres, as the README says
    small = load_stone_mesh(SHARED / "meshes" / name, target_size_m=0.06)
    assert small.mesh.extents.max() == pytest.approx(0.06)
    assert render(World(small), 30.0, 0.0, supersample=1).mask.sum() > 500


# Rendering --------------------------------------------------------------------------------------
def test_stone_rays_go_through_embree(world):
    assert isinstance(world.stone.mesh.ray, ray_pyembree.RayMeshIntersector)


def test_render_outputs_have_the_rig_shape_and_types(world):
    out = render(world, 30.0, 45.0)
    h, w = world.rig.height, world.rig.width
    assert out.radiance.shape == (h, w, 3) and out.radiance.dtype == np.float32
    assert out.mask.shape == (h, w) and out.mask.dtype == bool
    assert out.depth.dtype == np.float32 and out.alpha.dtype == np.float32
    np.testing.assert_array_equal(out.mask, out.alpha >= 0.5)
    assert np.all(out.depth[out.alpha == 0] == 0) and np.all(out.depth[out.mask] > 0)
    assert np.isfinite(out.radiance).all() and out.radiance.min() >= 0


def test_the_same_view_renders_identically_and_its_timing_is_reported(world):
    render(world, 20.0, 40.0)  # warm the caches (contact shadow, camera rays)
    wall, cpu, outs = [], [], []
    for _ in range(3):
        start, start_cpu = time.perf_counter(), time.process_time()
        outs.append(render(world, 20.0, 40.0, supersample=2))
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    size = f"{world.rig.width}x{world.rig.height}"
    print(f"\nrender {size} supersample 2: wall min {min(wall):.3f} s, cpu min {min(cpu):.3f} s")
    for out in outs[1:]:
        np.testing.assert_array_equal(out.radiance, outs[0].radiance)
        np.testing.assert_array_equal(out.depth, outs[0].depth)


def test_mask_equals_the_projection_of_the_mesh(world):
    """Pixel-centre sampling (supersample 1) against the union of the projected triangles."""
    rig, elevation, azimuth = world.rig, 35.0, 120.0
    mask = render(world, elevation, azimuth, supersample=1).mask
    uv = _project(world.stone.mesh.vertices, elevation, azimuth, rig) - 0.5  # cv2: pixel centres at integers
    fixed = np.round(uv * 16).astype(np.int32)[world.stone.mesh.faces]  # [F, 3, 2], 4 fractional bits
    silhouette = np.zeros((rig.height, rig.width), np.uint8)
    for triangle in fixed:  # one by one: fillPoly would XOR the overlapping front and back faces
        cv2.fillConvexPoly(silhouette, triangle, 1, lineType=cv2.LINE_8, shift=4)
    silhouette = silhouette.astype(bool)
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert not (mask & ~silhouette).any()
    assert not (silhouette & ~grown).any()  # cv2 also fills pixels its edges touch: at most one ring more
    assert (mask & silhouette).sum() / (mask | silhouette).sum() > 0.95


def test_depth_puts_pixels_back_onto_the_stone_surface(world):
    rig, elevation, azimuth = world.rig, 50.0, 10.0
    out = render(world, elevation, azimuth, supersample=1)
    c2w = camera_to_turntable(elevation, azimuth, rig)
    eye, dirs = camera_rays(rig, c2w, 1)
    rows, cols = np.nonzero(out.mask)
    pick = np.random.default_rng(0).choice(len(rows), 200, replace=False)
    ray = dirs[rows[pick] * rig.width + cols[pick]].astype(float)
    points = eye + ray * (out.depth[rows[pick], cols[pick]] / (ray @ c2w[:3, 2]))[:, None]
    _, distance, _ = trimesh.proximity.closest_point(world.stone.mesh, points)
    assert distance.max() < 1e-4


def test_coverage_is_fractional_only_on_the_silhouette_edge(world):
    out = render(world, 20.0, 0.0, supersample=4)
    partial = (out.alpha > 0) & (out.alpha < 1)
    edge = cv2.morphologyEx(out.mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)).astype(bool)
    assert partial.any() and np.all(edge[partial])


def test_plate_and_shot_differ_only_on_the_stone_and_its_contact_shadow(world):
    rig, elevation, azimuth = world.rig, 25.0, 70.0
    shot = render(world, elevation, azimuth, stone_present=True)
    plate = render(world, elevation, azimuth, stone_present=False)
    assert not plate.mask.any()
    changed = np.abs(shot.radiance - plate.radiance).max(axis=2) > 1e-4
    assert changed[shot.mask].mean() > 0.95
    shadow = changed & (shot.alpha == 0)  # off the stone, yet changed
    assert shadow.sum() > 100
    darker = shot.radiance.mean(axis=2) < plate.radiance.mean(axis=2)
    assert darker[shadow].all()
    # shadow pixels look at the plate within the occlusion reach of the stone
    eye, dirs = camera_rays(rig, camera_to_turntable(elevation, azimuth, rig), 1)
    sample = np.random.default_rng(0).choice(np.flatnonzero(shadow.ravel()), 300)
    ray = dirs[sample].astype(float)
    on_plate = eye + ray * (-eye[2] / ray[:, 2])[:, None]
    _, distance, _ = trimesh.proximity.closest_point(world.stone.mesh, on_plate)
    assert distance.max() < world.contact_shadow_reach_m + 0.005


def test_the_operator_flag_removes_the_stone(world):
    plate_world = World(world.stone, stone_present=False)
    np.testing.assert_array_equal(
        render(plate_world, 25.0, 70.0).radiance, render(world, 25.0, 70.0, stone_present=False).radiance
    )


def test_the_empty_lab_looks_the_same_from_every_turn(world):
    """Backdrop, light and chart stand in the lab and the bare plate is round: only the stone turns."""
    a = render(world, 15.0, 0.0, stone_present=False).radiance
    b = render(world, 15.0, 137.0, stone_present=False).radiance
    np.testing.assert_allclose(a, b, atol=1e-5)
    assert not np.allclose(render(world, 15.0, 0.0).radiance, render(world, 15.0, 137.0).radiance, atol=1e-3)


def test_the_chart_patches_keep_their_reflectance_ratios_in_a_low_plate(world):
    rig, elevation = world.rig, 10.0
    plate = render(world, elevation, 0.0, stone_present=False, supersample=2).radiance
    uv = _project(world.chart.patch_centres_lab(), elevation, 0.0, rig)  # lab = turntable at azimuth 0
    assert np.all((uv >= 3) & (uv <= [rig.width - 3, rig.height - 3]))
    cols, rows = np.floor(uv).astype(int).T
    rgb = plate[rows, cols]  # [24, 3]
    np.testing.assert_allclose(rgb / rgb[18], CHART_LINEAR_SRGB / CHART_LINEAR_SRGB[18], atol=2e-3)


# Sensor ----------------------------------------------------------------------------------------
def test_sensor_is_linear_in_exposure_and_iso_and_seeded():
    sensor = SensorModel(lens=SimLens.ideal())
    flat = np.full((64, 64, 3), 0.3, np.float32)

    def signal(exposure_s: float, iso: int) -> float:
        return sensor.expose(flat, exposure_s, iso, np.random.default_rng(0))[1::2, 0::2].mean() - sensor.black_level

    assert signal(0.02, 100) / signal(0.01, 100) == pytest.approx(2.0, rel=0.01)
    assert signal(0.01, 200) / signal(0.01, 100) == pytest.approx(2.0, rel=0.01)
    one = sensor.expose(flat, 0.01, 100, np.random.default_rng(5))
    np.testing.assert_array_equal(one, sensor.expose(flat, 0.01, 100, np.random.default_rng(5)))
    assert not np.array_equal(one, sensor.expose(flat, 0.01, 100, np.random.default_rng(6)))


def test_sensor_mosaic_is_rggb_with_noise_clipping_and_vignetting():
    sensor = SensorModel(lens=SimLens(exposure_jitter=False))
    red = np.zeros((64, 64, 3), np.float32)
    red[..., 0] = 0.5
    mosaic = sensor.expose(red, 0.01, 100, np.random.default_rng(0)).astype(float) - sensor.black_level
    assert mosaic[0::2, 0::2].mean() > 3 * abs(mosaic[1::2, 1::2].mean())
    bright = sensor.expose(np.full((64, 64, 3), 50.0, np.float32), 0.01, 100, np.random.default_rng(0))
    assert bright.max() == sensor.white_level
    grey = sensor.expose(np.full((240, 320, 3), 0.3, np.float32), 0.01, 100, np.random.default_rng(0)).astype(float)
    green = grey[0::2, 1::2] - sensor.black_level  # [120, 160]
    falloff = sensor.vignetting(240, 320)[0::2, 1::2]
    assert green[:6, :6].mean() / green[57:63, 77:83].mean() == pytest.approx(
        falloff[:6, :6].mean() / falloff[57:63, 77:83].mean(), rel=0.03)
    assert falloff[0, 0] == pytest.approx(2 ** -0.6, rel=0.01)  # 0.6 stops down in the corner
    assert green[50:70, 70:90].std() > 5.0  # shot and read noise


def test_sensor_refuses_odd_frames():
    with pytest.raises(BadInputError, match="even"):
        SensorModel().expose(np.zeros((63, 64, 3), np.float32), 0.01, 100, np.random.default_rng(0))


# Frame source (the simulated camera's shutter) --------------------------------------------------
@dataclass
class Settings:
    exposure_s: float = 0.01
    iso: int = 100


def test_frame_source_renders_the_turntable_pose_as_a_dng(world):
    pose = {"x": 30.0, "y": 40.0}
    source = frame_source(world, lambda: (pose["x"], pose["y"]), SensorModel(), seed=3)
    data, name = source(Settings())
    assert name == "SIM_00001.DNG"
    assert source.last_pose == (40.0, 30.0)
    info = read_dng(data, source=name)
    assert info.raw_image.shape == (world.rig.height, world.rig.width)
    np.testing.assert_array_equal(source.last.mask, render(world, 40.0, 30.0).mask)
    pose["x"] = 31.0
    _, second = source(Settings())
    assert second == "SIM_00002.DNG" and source.last_pose == (40.0, 31.0)


def test_frame_source_is_deterministic_per_seed_and_shot(world):
    one = frame_source(world, lambda: (0.0, 20.0), SensorModel(), seed=9)(Settings())[0]
    two = frame_source(world, lambda: (0.0, 20.0), SensorModel(), seed=9)(Settings())[0]
    other = frame_source(world, lambda: (0.0, 20.0), SensorModel(), seed=10)(Settings())[0]
    assert one == two and one != other


# sim_truth ------------------------------------------------------------------------------------
def test_sim_truth_holds_the_mesh_cameras_and_masks(world, tmp_path):
    frames = [("raw/e20_a000.dng", 20.0, 0.0), ("raw/e20_a090.dng", 20.0, 90.0)]
    write_sim_truth(tmp_path, world, frames)
    mesh = trimesh.load_mesh(tmp_path / "sim_truth" / "mesh.ply")
    assert mesh.is_watertight
    np.testing.assert_allclose(mesh.bounds, world.stone.mesh.bounds, atol=1e-6)
    cameras = json.loads((tmp_path / "sim_truth" / "cameras.json").read_text())["frames"]
    assert [c["file"] for c in cameras] == [f for f, _, _ in frames]
    np.testing.assert_allclose(cameras[1]["camera_to_world"], camera_to_turntable(20.0, 90.0, world.rig))
    np.testing.assert_allclose(cameras[1]["K"], world.rig.intrinsics())
    assert (cameras[1]["width"], cameras[1]["height"]) == (world.rig.width, world.rig.height)
    png = np.array(Image.open(mask_path_for(tmp_path, "raw/e20_a090.dng")))
    assert png.dtype == np.uint8 and set(np.unique(png)) <= {0, 255}
    np.testing.assert_array_equal(png == 255, render(world, 20.0, 90.0).mask)


def test_sim_truth_keeps_the_noise_free_exposed_image_also_at_a_training_width(world, tmp_path):
    file = "raw/e20_a090.dng"
    write_sim_truth(tmp_path, world, [(file, 20.0, 90.0)])
    out = render(world, 20.0, 90.0, stone_present=True)
    truth, expected = read_truth_image(image_path_for(tmp_path, file)), TruthImage.of(out)
    np.testing.assert_allclose(truth.exposed, expected.exposed, rtol=2e-3, atol=1e-4)  # half floats
    np.testing.assert_allclose(truth.stone, expected.stone, rtol=2e-3, atol=1e-4)
    np.testing.assert_allclose(truth.alpha, out.alpha, atol=1e-3)
    assert np.all(truth.stone[out.alpha == 0] == 0) and np.all(truth.exposed[out.alpha == 1] == truth.stone[out.alpha == 1])
    # what an ideal develop makes: the lens's falloff taken out
    assert truth.exposed[0, 0, 1] == pytest.approx(out.radiance[0, 0, 1], rel=2e-3)
    w, h = world.rig.width // 2, world.rig.height // 2
    half = true_images_at(tmp_path, w, [file])[file]
    assert image_path_for(tmp_path, file, w).is_file()
    # a render is a box filter, so averaging it down is rendering at the smaller size with the same samples
    direct = render(World(world.stone, rig=world.rig.scaled(w, h), lens=world.lens), 20.0, 90.0, stone_present=True,
                    supersample=4)
    np.testing.assert_allclose(half.alpha, direct.alpha, atol=2e-3)
    np.testing.assert_allclose(half.stone, TruthImage.of(direct).stone, atol=5e-3)


def test_truth_frames_are_added_one_by_one_on_resume(world, tmp_path):
    write_truth_frame(tmp_path, world, "raw/b.dng", 20.0, 9.0)
    write_truth_frame(tmp_path, world, "raw/a.dng", 20.0, 0.0)
    write_truth_frame(tmp_path, world, "raw/b.dng", 20.0, 18.0)  # re-shot after a crash: replaced, not doubled
    cameras = json.loads((tmp_path / "sim_truth" / "cameras.json").read_text())["frames"]
    assert [(c["file"], c["azimuth_deg"]) for c in cameras] == [("raw/a.dng", 0.0), ("raw/b.dng", 18.0)]
    assert (tmp_path / "sim_truth" / "mesh.ply").is_file()
    assert sorted(p.name for p in (tmp_path / "sim_truth" / "masks").iterdir()) == ["a.png", "b.png"]


def test_a_batch_of_truth_frames_replaces_its_own_and_keeps_the_others(world, tmp_path):
    write_truth_frame(tmp_path, world, "raw/a.dng", 20.0, 0.0)
    write_truth_frame(tmp_path, world, "raw/b.dng", 20.0, 9.0)
    empty = np.zeros((world.rig.height, world.rig.width), bool)
    write_truth_frames(tmp_path, world, [TruthFrame("raw/c.dng", 20.0, 27.0, empty),
                                         TruthFrame("raw/b.dng", 20.0, 18.0, empty)])
    cameras = json.loads((tmp_path / "sim_truth" / "cameras.json").read_text())["frames"]
    assert [(c["file"], c["azimuth_deg"]) for c in cameras] == [("raw/a.dng", 0.0), ("raw/b.dng", 18.0),
                                                                ("raw/c.dng", 27.0)]
    assert not cv2.imread(str(tmp_path / "sim_truth" / "masks" / "b.png"), cv2.IMREAD_GRAYSCALE).any()


def test_truth_refuses_frames_outside_the_scan_folder(world, tmp_path):
    with pytest.raises(ScanFolderError, match="outside"):
        write_truth_frame(tmp_path, world, "../elsewhere.dng", 20.0, 0.0)


def test_developing_the_dng_gives_back_the_scene_colours(world):
    """Render -> sensor -> DNG -> LibRaw linear sRGB develop: the chart's colours survive the chain."""
    rig, elevation = world.rig, 10.0
    sensor = SensorModel(lens=SimLens.ideal(), read_noise_dn=0.5)
    data, _ = frame_source(world, lambda: (0.0, elevation), sensor, seed=1)(Settings(exposure_s=1 / 30))
    with rawpy.imread(io.BytesIO(data)) as raw:
        developed = raw.postprocess(
            gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
            output_color=rawpy.ColorSpace.sRGB, adjust_maximum_thr=0.0,
        ).astype(float)  # [H, W, 3]
    cols, rows = np.floor(_project(world.chart.patch_centres_lab(), elevation, 0.0, rig)).astype(int).T
    patches = np.stack([developed[r - 1 : r + 2, c - 1 : c + 2].mean(axis=(0, 1)) for r, c in zip(rows, cols)])
    expected = CHART_LINEAR_SRGB / CHART_LINEAR_SRGB[18]
    np.testing.assert_allclose(patches / patches[18], expected, atol=0.03)
