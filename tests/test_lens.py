"""Lenses: parsing and the fold check, self-calibration by bundle adjustment, the COLMAP export."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from station.errors import BadInputError
from station.process import sfm
from station.process.colmap_export import colmap_model, write_colmap_model
from station.process.lens import Lens, check_unfolded, displacement_px, lens_from_colmap, undistortion
from station.process.rig_model import RigModel
from station.formats.transforms import PinholeCamera
from station.process.transforms import PosedFrame, Transforms
from station.rig_geometry import RigGeometry, look_at_c2w
from station.scanfolder import ScanFolder

W, H = 320, 240
TRUE_PARAMS = [300.0, 300.0, 163.0, 118.0, -0.1, 0.02, 0.001, -0.0005]  # a kit zoom at its wide end


def ring_poses(elevations=(15.0, 40.0), count: int = 12, distance: float = 0.5) -> list[tuple[float, np.ndarray]]:
    out = []
    for e in elevations:
        er = np.deg2rad(e)
        for a in np.linspace(0.0, 2 * np.pi, count, endpoint=False):
            eye = distance * np.array([np.cos(er) * np.cos(a), np.cos(er) * np.sin(a), np.sin(er)])
            out.append((e, look_at_c2w(eye, np.zeros(3))))
    return out


def observed_scene(noise_px: float = 0.2, seed: int = 0, params: list[float] = TRUE_PARAMS, spread: float = 0.2,
                   ) -> tuple[pycolmap.Reconstruction, list[tuple[float, np.ndarray]]]:
    """Points seen through the true distorted camera by fixed ring poses; the model starts from a pinhole guess."""
    rng = np.random.default_rng(seed)
    truth = pycolmap.Camera(model="OPENCV", width=W, height=H, params=params, camera_id=1)
    start = pycolmap.Camera(model="OPENCV", width=W, height=H, params=[310, 310, W / 2, H / 2, 0, 0, 0, 0], camera_id=1)
    points = rng.uniform(-spread, spread, (400, 3))
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(start)
    tracks: dict[int, list[tuple[int, int]]] = {}
    poses = ring_poses()
    for image_id, (e, c2w) in enumerate(poses, start=1):
        w2c = np.linalg.inv(c2w)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = truth.img_from_cam(cam) + rng.normal(0.0, noise_px, (len(points), 2))
        seen = np.flatnonzero((cam[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H))
        image = pycolmap.Image(name=f"e{e:g}_{image_id:02d}.png", camera_id=1, image_id=image_id,
                               points2D=pycolmap.Point2DList([pycolmap.Point2D(uv[k]) for k in seen]))
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
        for j, k in enumerate(seen):
            tracks.setdefault(int(k), []).append((image_id, j))
    for k, elements in tracks.items():
        track = pycolmap.Track()
        for image_id, j in elements:
            track.add_element(image_id, j)
        rec.add_point3D(points[k] + rng.normal(0.0, 0.002, 3), track, np.array([90, 80, 70], np.uint8))
    return rec, poses


def test_self_calibration_recovers_a_known_lens_with_the_rig_poses_held():
    rec, poses = observed_scene()
    before = np.concatenate(list(sfm.reprojection_errors(rec).values())).mean()
    rec, note = sfm.self_calibrate(rec, sfm.SfmSettings(), hold_poses=True)
    assert note is None
    camera = rec.cameras[1]
    fx, fy, cx, cy, k1, k2, p1, p2 = camera.params
    assert fx == pytest.approx(300.0, rel=0.005) and cx == pytest.approx(163.0, abs=0.5) and cy == pytest.approx(118.0, abs=0.5)
    assert k1 == pytest.approx(-0.1, abs=0.006) and p1 == pytest.approx(0.001, abs=5e-4)
    errors = sfm.reprojection_errors(rec)
    after = np.concatenate(list(errors.values())).mean()
    assert before > 2.0 and after < 0.3  # noise of 0.2 px per axis: a mean distance of about 0.25 px
    for image in rec.images.values():  # the rig's poses did not move
        c2w = dict((f"e{e:g}_{i:02d}.png", p) for i, (e, p) in enumerate(poses, start=1))[image.name]
        np.testing.assert_allclose(sfm.c2w_of(image), c2w, atol=1e-9)
    lens = lens_from_colmap(camera, "test")
    assert lens.model == "OPENCV" and displacement_px(lens) > 3.0 and undistortion(lens, 0.1) is not None


def test_self_calibration_keeps_the_prior_when_the_lens_is_unobservable_or_fits_no_better():
    small, _ = observed_scene(spread=0.05)  # a stone in the middle of the frame
    kept, note = sfm.self_calibrate(small, sfm.SfmSettings(), hold_poses=True)
    assert kept is small and "features reach" in note and kept.cameras[1].params[4] == 0.0
    pinhole, _ = observed_scene(params=[310, 310, W / 2, H / 2, 0, 0, 0, 0])  # the prior is already right
    kept, note = sfm.self_calibrate(pinhole, sfm.SfmSettings(), hold_poses=True)
    assert kept is pinhole and "moved the mean error only" in note


def test_the_fold_check_refuses_a_radial_map_that_turns_back_inside_the_image():
    intr = PinholeCamera(W, H, 200.0, 200.0, W / 2, H / 2)  # corners at a normalised radius of 1.0
    # r (1 + k1 r^2) peaks at r = 1 / sqrt(-3 k1) with height 2 / 3 of that: 1.22 for k1 = -0.1, 0.99 for -0.15
    check_unfolded(Lens(intr, "OPENCV", (-0.1, 0, 0, 0, 0, 0, 0, 0)), "mild")
    with pytest.raises(BadInputError, match=r"strong: OPENCV distortion .* folds the image: .* turns back 199 px"):
        check_unfolded(Lens(intr, "OPENCV", (-0.15, 0, 0, 0, 0, 0, 0, 0)), "strong")
    with pytest.raises(BadInputError, match="fish: OPENCV_FISHEYE distortion .* folds"):
        check_unfolded(Lens(intr, "OPENCV_FISHEYE", (-0.5, 0, 0, 0)), "fish")


def test_a_calibrated_lens_joins_the_rig_model_and_survives_its_json(tmp_path):
    nominal = RigModel.nominal(RigGeometry(), [15.0, 40.0])
    lens = Lens(nominal.intrinsics, "OPENCV", (-0.1, 0.02, 0.001, -0.0005, 0.0, 0.0, 0.0, 0.0))
    model = RigModel(nominal.intrinsics, nominal.elevation_poses, kind="calibrated", distortion=lens)
    model.save(tmp_path / "rig.json")
    back = RigModel.load(tmp_path / "rig.json")
    assert back.lens() == lens and RigModel.load(tmp_path / "rig.json").lens().scaled(640, 480).coefficients == lens.coefficients
    assert nominal.lens().model == "PINHOLE" and not nominal.lens().distorted
    with pytest.raises(BadInputError, match="lens's intrinsics differ"):
        RigModel(nominal.intrinsics, nominal.elevation_poses, distortion=lens.scaled(640, 480))


def test_the_colmap_export_round_trips_through_pycolmap_with_undistorted_tracks(tmp_path):
    rec, poses = observed_scene(noise_px=0.0)
    rec, _ = sfm.self_calibrate(rec, sfm.SfmSettings(), hold_poses=True)
    lens = lens_from_colmap(rec.cameras[1], "test")
    target = undistortion(lens).target
    frames = [PosedFrame(f"images/{im.name}", sfm.c2w_of(im)) for im in sorted(rec.images.values(), key=lambda i: i.name)]
    transforms = Transforms(target, frames)
    folder = write_colmap_model(ScanFolder(tmp_path), colmap_model(transforms, (np.zeros((0, 3)), np.zeros((0, 3))), rec, lens))
    back = pycolmap.Reconstruction(str(folder))
    camera = back.cameras[1]
    assert camera.model.name == "PINHOLE" and back.num_reg_images() == len(poses)
    assert back.num_points3D() == rec.num_points3D()
    for frame in frames:
        image = next(im for im in back.images.values() if im.name == frame.file_path.split("/")[1])
        np.testing.assert_allclose(sfm.c2w_of(image), frame.c2w, atol=1e-9)
    errors = np.concatenate(list(sfm.reprojection_errors(back).values()))
    assert errors.mean() < 0.05  # undistorted observations fit the pinhole as the distorted fit the lens


def test_an_exported_cloud_without_tracks_round_trips_too(tmp_path):
    intr = PinholeCamera(W, H, 300.0, 300.0, W / 2, H / 2)
    frames = [PosedFrame(f"images/v{i}.png", c2w) for i, (_, c2w) in enumerate(ring_poses(count=4))]
    xyz, rgb = np.random.default_rng(1).normal(size=(50, 3)), np.full((50, 3), 7, np.uint8)
    folder = write_colmap_model(ScanFolder(tmp_path), colmap_model(Transforms(intr, frames), (xyz, rgb)))
    back = pycolmap.Reconstruction(str(folder))
    got = np.array(sorted(p.xyz.tolist() for p in back.points3D.values()))
    np.testing.assert_allclose(got, np.array(sorted(xyz.tolist())), atol=1e-12)
    assert back.cameras[1].params.tolist() == [300.0, 300.0, W / 2, H / 2]
