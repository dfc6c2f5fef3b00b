"""`station import`: nerfstudio / NeRF-synthetic, COLMAP and IDR (DTU) datasets into a posed scan folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image
from scipy import ndimage

from station.errors import BadInputError
from station.process.importers import ImportSettings, import_dataset
from station.process.poses import write_point_ply
from station.process.rig_model import rotation_angle_deg, umeyama
from station.process.transforms import read_transforms
from station.rig_geometry import look_at_c2w, opencv_to_opengl
from station.scanfolder import ScanFolder

W, H, F = 160, 120, 150.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
QUICK = ImportSettings(hull_resolution=24)  # where the starting cloud is not what is under test
BALL_CENTRE, BALL_RADIUS = np.array([0.0, 0.0, 0.3]), 0.25  # source units


def ring_cameras(count: int = 12, distance: float = 2.0, elevation_deg: float = 30.0) -> list[np.ndarray]:
    """OpenCV camera-to-world poses on a ring around BALL_CENTRE, +z up."""
    e = np.deg2rad(elevation_deg)
    out = []
    for a in np.linspace(0.0, 2 * np.pi, count, endpoint=False):
        eye = BALL_CENTRE + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        out.append(look_at_c2w(eye, BALL_CENTRE))
    return out


def ball_rgba(c2w: np.ndarray) -> np.ndarray:
    """RGBA [H, W, 4] of a ball: alpha is its silhouette, its edge pixels partly covered (200)."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = c2w[:3, 3] - BALL_CENTRE
    b = d @ oc
    hit = b * b - (oc @ oc - BALL_RADIUS**2) > 0
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., :3] = 40
    rgba[hit] = (200, 150, 90, 255)
    inner = hit.copy()
    inner[1:-1, 1:-1] = hit[1:-1, 1:-1] & hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
    rgba[hit & ~inner, 3] = 200
    return rgba


def write_nerfstudio(src: Path, cams: list[np.ndarray], synthetic: bool = False) -> None:
    (src / "train").mkdir(parents=True)
    frames = []
    for i, c2w in enumerate(cams):
        Image.fromarray(ball_rgba(c2w)).save(src / "train" / f"r_{i}.png")
        path = f"./train/r_{i}" if synthetic else f"train/r_{i}.png"
        frames.append({"file_path": path, "transform_matrix": opencv_to_opengl(c2w).tolist()})
    data = {"frames": frames}
    if synthetic:
        data["camera_angle_x"] = 2 * np.arctan(0.5 * W / F)
    else:
        data.update(fl_x=F, fl_y=F, cx=W / 2, cy=H / 2, w=W, h=H)
    (src / ("transforms_train.json" if synthetic else "transforms.json")).write_text(json.dumps(data))


def test_nerfstudio_import_flips_opengl_poses_to_opencv_and_takes_masks_from_alpha(tmp_path):
    cams = ring_cameras()
    write_nerfstudio(tmp_path / "src", cams)
    report = import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", QUICK)
    assert report.frames == 12 and report.masks == "alpha" and report.orient == "keep"
    scan = ScanFolder(tmp_path / "scan")
    transforms = read_transforms(scan)
    assert transforms.intrinsics.fx == pytest.approx(F) and transforms.intrinsics.width == W
    for frame, c2w in zip(transforms.frames, cams):
        np.testing.assert_allclose(frame.c2w, c2w, atol=1e-9)
        mask = np.asarray(Image.open(scan.resolve_inside(frame.mask_path)))
        np.testing.assert_array_equal(mask, ball_rgba(c2w)[..., 3])  # the alpha channel as given: coverage
    raw = json.loads(scan.transforms_path.read_text())
    np.testing.assert_allclose(raw["frames"][0]["transform_matrix"], opencv_to_opengl(cams[0]), atol=1e-9)


def test_masks_without_points_give_a_visual_hull_cloud_on_the_object(tmp_path):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=16))
    report = import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", ImportSettings(hull_resolution=64))
    assert report.init_cloud == "visual_hull" and report.points > 300
    body = (ScanFolder(tmp_path / "scan").poses_dir / "points3d.ply").read_bytes().split(b"end_header\n", 1)[1]
    xyz = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])["xyz"]
    radial = np.linalg.norm(xyz - BALL_CENTRE, axis=1)
    # A hull from one ring over-estimates the ball top and bottom, never the ring's equator.
    assert np.median(radial) == pytest.approx(BALL_RADIUS, rel=0.25) and radial.min() > 0.8 * BALL_RADIUS


def test_nerf_synthetic_camera_angle_x_and_suffixless_paths_with_explicit_units(tmp_path):
    cams = ring_cameras()
    write_nerfstudio(tmp_path / "src", cams, synthetic=True)
    report = import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", ImportSettings(units_to_m=0.1, hull_resolution=24))
    assert report.units_to_m == 0.1
    transforms = read_transforms(ScanFolder(tmp_path / "scan"))
    assert transforms.intrinsics.fx == pytest.approx(F) and transforms.intrinsics.cy == pytest.approx(H / 2)
    for frame, c2w in zip(transforms.frames, cams):
        np.testing.assert_allclose(frame.c2w[:3, 3], 0.1 * c2w[:3, 3], atol=1e-9)
        np.testing.assert_allclose(frame.c2w[:3, :3], c2w[:3, :3], atol=1e-9)


def colmap_world_cameras() -> tuple[list[np.ndarray], np.ndarray]:
    """The ring seen in a typical COLMAP gauge: rotated (up is -y), shifted, in centimetres."""
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # z-up -> y-down world
    cams = []
    for c2w in ring_cameras():
        moved = np.eye(4)
        moved[:3, :3] = rot @ c2w[:3, :3]
        moved[:3, 3] = 100.0 * rot @ c2w[:3, 3] + np.array([5.0, -3.0, 7.0])
        cams.append(moved)
    return cams, rot


def write_colmap(src: Path, cams: list[np.ndarray], params: list[float] | None = None) -> None:
    rec = pycolmap.Reconstruction()
    model = "PINHOLE" if params is None else "OPENCV"
    camera = pycolmap.Camera(model=model, width=W, height=H, params=params or [F, F, W / 2, H / 2], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    (src / "images").mkdir(parents=True)
    for i, c2w in enumerate(cams):
        name = f"img{i:02d}.png"
        Image.fromarray(ball_rgba(c2w)[..., :3]).save(src / "images" / name)
        w2c = np.linalg.inv(c2w)
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    rec.add_point3D(np.array([5.0, -3.0, 7.0]), pycolmap.Track(), np.array([10, 20, 30], dtype=np.uint8))
    (src / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(src / "sparse" / "0"))


def test_colmap_import_converts_units_and_keeps_axes_when_asked(tmp_path):
    cams, _ = colmap_world_cameras()
    write_colmap(tmp_path / "src", cams)
    report = import_dataset(tmp_path / "src", "colmap", tmp_path / "scan", ImportSettings(units_to_m=0.01, orient="keep"))
    assert report.init_cloud == "source" and report.points == 1 and report.masks == "none"
    transforms = read_transforms(ScanFolder(tmp_path / "scan"))
    assert [Path(f.file_path).name for f in transforms.frames][0] == "0000_img00.png"
    for frame, c2w in zip(transforms.frames, cams):
        np.testing.assert_allclose(frame.c2w[:3, 3], 0.01 * c2w[:3, 3], atol=1e-9)
        assert rotation_angle_deg(frame.c2w[:3, :3], c2w[:3, :3]) < 1e-6


def test_colmap_import_turns_the_camera_ring_upright_by_default(tmp_path):
    cams, _ = colmap_world_cameras()
    write_colmap(tmp_path / "src", cams)
    report = import_dataset(tmp_path / "src", "colmap", tmp_path / "scan", ImportSettings(units_to_m=0.01))
    assert report.orient == "ring"
    frames = read_transforms(ScanFolder(tmp_path / "scan")).frames
    centres = np.array([f.c2w[:3, 3] for f in frames])
    truth = np.array([c[:3, 3] for c in ring_cameras()])
    assert np.ptp(centres[:, 2]) < 1e-9 and centres[:, 2].min() > 0  # ring horizontal, cameras above
    scale, rot, _ = umeyama(centres, truth)
    assert scale == pytest.approx(1.0, abs=1e-9)  # metres
    assert rotation_angle_deg(rot, np.eye(3)) < 90.0 and abs(rot[2, 2] - 1.0) < 1e-9  # only a turn about z


DOTS = np.array([(x, y) for x in np.linspace(-0.4, 0.4, 7) for y in np.linspace(-0.28, 0.28, 5)])  # normalised
DOT_RADIUS = 0.02


def dots_image(camera: pycolmap.Camera, supersample: int = 3) -> np.ndarray:
    """Coverage [H, W] (0..255) of round dots at DOTS on a plane at z = 1, seen through `camera`'s lens.

    COLMAP's own model (cam_from_img) distorts here, an implementation independent of the OpenCV
    one the importer undistorts with; pixel centres sit at +0.5 as in COLMAP and nerfstudio.
    """
    s = supersample
    u, v = np.meshgrid((np.arange(W * s) + 0.5) / s, (np.arange(H * s) + 0.5) / s)
    ray = camera.cam_from_img(np.column_stack([u.ravel(), v.ravel()]))  # [N, 2] normalised
    d = np.min(np.linalg.norm(ray[:, None, :] - DOTS[None], axis=-1), axis=1)
    inside = (d < DOT_RADIUS).reshape(H * s, W * s).astype(np.float64)
    return np.rint(255 * inside.reshape(H, s, W, s).mean(axis=(1, 3))).astype(np.uint8)


def dot_errors_px(coverage: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Distance of each imaged dot's centroid from where a pinhole (fx, fy, cx, cy) puts its centre."""
    labels, count = ndimage.label(coverage > 0)
    centroids = np.array(ndimage.center_of_mass(coverage.astype(np.float64), labels, range(1, count + 1)))[:, ::-1] + 0.5
    expected = np.column_stack([fx * DOTS[:, 0] + cx, fy * DOTS[:, 1] + cy])
    seen = (expected[:, 0] > 4) & (expected[:, 0] < W - 4) & (expected[:, 1] > 4) & (expected[:, 1] < H - 4)
    assert count >= seen.sum() > 10
    return np.array([np.min(np.linalg.norm(centroids - e, axis=1)) for e in expected[seen]])


def distorted_dataset(src: Path, camera: pycolmap.Camera, fmt: str, nerfstudio: dict | None = None) -> None:
    """Three views of the dot plane through a distorted camera, as nerfstudio (RGBA, alpha = dots) or COLMAP."""
    cover = dots_image(camera)
    cams = ring_cameras(count=3)
    if fmt == "colmap":
        rec = pycolmap.Reconstruction()
        rec.add_camera_with_trivial_rig(camera)
        (src / "images").mkdir(parents=True)
        for i, c2w in enumerate(cams):
            Image.fromarray(np.repeat(cover[..., None], 3, axis=2)).save(src / "images" / f"img{i}.png")
            image = pycolmap.Image(name=f"img{i}.png", camera_id=camera.camera_id, image_id=i + 1)
            rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.linalg.inv(c2w)[:3, :4]))
        (src / "sparse" / "0").mkdir(parents=True)
        rec.write_binary(str(src / "sparse" / "0"))
        return
    (src / "train").mkdir(parents=True)
    rgba = np.dstack([np.full((H, W, 3), 120, np.uint8), cover])
    frames = []
    for i, c2w in enumerate(cams):
        Image.fromarray(rgba).save(src / "train" / f"r_{i}.png")
        frames.append({"file_path": f"train/r_{i}.png", "transform_matrix": opencv_to_opengl(c2w).tolist()})
    k = camera.calibration_matrix()
    data = dict(fl_x=k[0, 0], fl_y=k[1, 1], cx=k[0, 2], cy=k[1, 2], w=W, h=H, frames=frames, **(nerfstudio or {}))
    (src / "transforms.json").write_text(json.dumps(data))


def _camera(model: str, params: list[float]) -> pycolmap.Camera:
    return pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1)


COLMAP_LENSES = {
    "SIMPLE_RADIAL": [F, W / 2, H / 2, -0.25],
    "RADIAL": [F, W / 2 + 3, H / 2 - 2, -0.22, 0.05],
    "OPENCV": [F, F * 1.01, W / 2, H / 2, -0.2, 0.04, 0.004, -0.003],
    "FULL_OPENCV": [F, F, W / 2, H / 2, -0.2, 0.03, 0.002, 0.002, 0.01, 0.05, 0.0, 0.0],
    "OPENCV_FISHEYE": [F, F, W / 2, H / 2, 0.08, -0.02, 0.01, 0.0],
}


@pytest.mark.parametrize("model", sorted(COLMAP_LENSES))
def test_colmap_distorted_cameras_are_undistorted_to_a_pinhole_on_import(tmp_path, model):
    camera = _camera(model, COLMAP_LENSES[model])
    distorted_dataset(tmp_path / "src", camera, "colmap")
    report = import_dataset(tmp_path / "src", "colmap", tmp_path / "scan", ImportSettings(orient="keep"))
    assert any("undistorted" in f for f in report.flags)
    scan = ScanFolder(tmp_path / "scan")
    t = read_transforms(scan)
    raw = json.loads(scan.transforms_path.read_text())
    assert raw["k1"] == raw["k2"] == raw["p1"] == raw["p2"] == 0.0
    image = np.asarray(Image.open(scan.resolve_inside(t.frames[0].file_path)).convert("L"))
    errors = dot_errors_px(image, t.intrinsics.fx, t.intrinsics.fy, t.intrinsics.cx, t.intrinsics.cy)
    assert errors.max() < 0.35, errors  # each dot lands where the written pinhole puts it
    back = pycolmap.Reconstruction(str(scan.poses_dir / "colmap"))  # the COLMAP model beside it agrees
    i = t.intrinsics
    assert back.cameras[1].model.name == "PINHOLE" and back.num_reg_images() == 3
    np.testing.assert_allclose(back.cameras[1].params, [i.fx, i.fy, i.cx, i.cy])


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_nerfstudio_distorted_cameras_and_their_alpha_masks_are_undistorted_alike(tmp_path, model):
    if model == "OPENCV":
        camera, extra = _camera("OPENCV", [F, F, W / 2, H / 2, -0.22, 0.04, 0.003, -0.002]), \
            {"camera_model": "OPENCV", "k1": -0.22, "k2": 0.04, "p1": 0.003, "p2": -0.002}
    else:
        camera, extra = _camera("OPENCV_FISHEYE", [F, F, W / 2, H / 2, 0.1, -0.03, 0.01, 0.002]), \
            {"camera_model": "OPENCV_FISHEYE", "k1": 0.1, "k2": -0.03, "k3": 0.01, "k4": 0.002}
    distorted_dataset(tmp_path / "src", camera, "nerfstudio", extra)
    report = import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", QUICK)
    assert report.masks == "alpha"
    scan = ScanFolder(tmp_path / "scan")
    t = read_transforms(scan)
    i = t.intrinsics
    mask = np.asarray(Image.open(scan.resolve_inside(t.frames[1].mask_path)))
    assert dot_errors_px(mask, i.fx, i.fy, i.cx, i.cy).max() < 0.35
    assert 0 < (mask[(mask > 0) & (mask < 255)]).size  # coverage stays coverage at the dot edges


def test_a_distortion_that_folds_the_image_is_refused(tmp_path):
    distorted_dataset(tmp_path / "src", _camera("RADIAL", [F, W / 2, H / 2, -0.6, 0.0]), "colmap")
    with pytest.raises(BadInputError, match=r"sparse/0: OPENCV distortion .*folds the image"):
        import_dataset(tmp_path / "src", "colmap", tmp_path / "scan")
    assert not (tmp_path / "scan" / "poses").exists()


def test_a_camera_model_we_cannot_handle_is_refused_naming_file_and_model(tmp_path):
    distorted_dataset(tmp_path / "a", _camera("FOV", [F, F, W / 2, H / 2, 0.5]), "colmap")
    with pytest.raises(BadInputError, match=r"sparse/0: camera model FOV is not supported"):
        import_dataset(tmp_path / "a", "colmap", tmp_path / "scan_a")
    distorted_dataset(tmp_path / "b", _camera("PINHOLE", [F, F, W / 2, H / 2]), "nerfstudio",
                      {"camera_model": "EQUIRECTANGULAR"})
    with pytest.raises(BadInputError, match=r"transforms.json: camera_model 'EQUIRECTANGULAR' is not supported"):
        import_dataset(tmp_path / "b", "nerfstudio", tmp_path / "scan_b")


def test_a_mask_whose_size_differs_from_its_image_is_refused(tmp_path):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=3))
    Image.fromarray(np.zeros((H // 2, W // 2), np.uint8)).save(tmp_path / "src" / "small.png")
    data = json.loads((tmp_path / "src" / "transforms.json").read_text())
    data["frames"][2]["mask_path"] = "small.png"
    (tmp_path / "src" / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(BadInputError, match=r"small.png: mask size \(80, 60\) differs from its image's \(160, 120\)"):
        import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", QUICK)


def write_idr(src: Path, cams_mm: list[np.ndarray]) -> None:
    (src / "image").mkdir(parents=True)
    (src / "mask").mkdir()
    arrays = {}
    for i, c2w in enumerate(cams_mm):
        rgba = ball_rgba(np.diag([1, 1, 1, 1.0]) @ np.block([[c2w[:3, :3], c2w[:3, 3:] / 1000], [0, 0, 0, 1]]))
        Image.fromarray(rgba[..., :3]).save(src / "image" / f"{i:06d}.png")
        Image.fromarray(rgba[..., 3]).save(src / "mask" / f"{i:03d}.png")
        w2c = np.linalg.inv(c2w)
        p = np.eye(4)
        p[:3, :4] = K @ w2c[:3, :4]
        arrays[f"world_mat_{i}"] = p
        arrays[f"scale_mat_{i}"] = np.diag([300.0, 300.0, 300.0, 1.0])
    np.savez(src / "cameras.npz", **arrays)


def test_idr_import_decomposes_projection_matrices_and_converts_millimetres_to_metres(tmp_path):
    cams_m = ring_cameras()
    cams_mm = [np.block([[c[:3, :3], 1000.0 * c[:3, 3:]], [np.array([[0, 0, 0, 1.0]])]]) for c in cams_m]
    write_idr(tmp_path / "src", cams_mm)
    report = import_dataset(tmp_path / "src", "idr", tmp_path / "scan", ImportSettings(orient="keep", hull_resolution=24))
    assert report.units_to_m == 0.001 and report.masks == "files"
    transforms = read_transforms(ScanFolder(tmp_path / "scan"))
    assert transforms.intrinsics.fx == pytest.approx(F) and transforms.intrinsics.cx == pytest.approx(W / 2)
    for frame, c2w in zip(transforms.frames, cams_m):
        np.testing.assert_allclose(frame.c2w[:3, 3], c2w[:3, 3], atol=1e-9)
        assert rotation_angle_deg(frame.c2w[:3, :3], c2w[:3, :3]) < 1e-6


def test_a_source_path_escaping_its_folder_is_refused_naming_the_field(tmp_path):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=3))
    data = json.loads((tmp_path / "src" / "transforms.json").read_text())
    data["frames"][1]["file_path"] = "../outside.png"
    (tmp_path / "src" / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(BadInputError, match=r"frames\[1\]\.file_path.*outside"):
        import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan")


def test_missing_focal_length_is_refused_naming_the_field(tmp_path):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=3))
    data = json.loads((tmp_path / "src" / "transforms.json").read_text())
    del data["fl_x"]
    (tmp_path / "src" / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(BadInputError, match="transforms.json: fl_x: missing"):
        import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan")


def test_unknown_format_is_refused(tmp_path):
    with pytest.raises(BadInputError, match="unknown format 'ply'"):
        import_dataset(tmp_path, "ply", tmp_path / "scan")  # type: ignore[arg-type]


def test_tampered_transforms_json_is_refused_on_read(tmp_path):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=3))
    import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", QUICK)
    scan = ScanFolder(tmp_path / "scan")
    good = json.loads(scan.transforms_path.read_text())
    bad_path = json.loads(json.dumps(good))
    bad_path["frames"][0]["mask_path"] = "/etc/passwd"
    scan.transforms_path.write_text(json.dumps(bad_path))
    with pytest.raises(BadInputError, match="outside the scan folder"):
        read_transforms(scan)
    bad_pose = json.loads(json.dumps(good))
    bad_pose["frames"][2]["transform_matrix"][0][0] = 3.0
    scan.transforms_path.write_text(json.dumps(bad_pose))
    with pytest.raises(BadInputError, match=r"frames\[2\]\.transform_matrix: upper 3x3 is not a rotation"):
        read_transforms(scan)
    bad_size = dict(good, w=-4)
    scan.transforms_path.write_text(json.dumps(bad_size))
    with pytest.raises(BadInputError, match="transforms.json: w: must lie in"):
        read_transforms(scan)


def test_point_ply_is_binary_with_colours(tmp_path):
    xyz = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    rgb = np.array([[1, 2, 3], [250, 251, 252]], dtype=np.uint8)
    write_point_ply(tmp_path / "p.ply", xyz, rgb)
    head, body = (tmp_path / "p.ply").read_bytes().split(b"end_header\n", 1)
    assert b"element vertex 2" in head and b"property uchar red" in head
    rec = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    np.testing.assert_array_equal(rec["xyz"], xyz.astype(np.float32))
    np.testing.assert_array_equal(rec["rgb"], rgb)


def test_colmap_images_are_never_looked_for_above_the_source_folder(tmp_path):
    cams, _ = colmap_world_cameras()
    write_colmap(tmp_path / "src", cams)
    for file in (tmp_path / "src" / "sparse" / "0").iterdir():
        file.rename(tmp_path / "src" / file.name)
    (tmp_path / "src" / "images").rename(tmp_path / "images")  # beside the source, not in it
    with pytest.raises(BadInputError, match="no images/ folder beside it inside"):
        import_dataset(tmp_path / "src", "colmap", tmp_path / "scan")


@pytest.mark.parametrize("link", ["image/000001.png", "image", "cameras.npz"])
def test_idr_files_linked_out_of_the_source_are_refused_unread(tmp_path, link):
    write_idr(tmp_path / "src", [np.block([[c[:3, :3], 1000.0 * c[:3, 3:]], [np.array([[0, 0, 0, 1.0]])]])
                                 for c in ring_cameras(count=3)])
    path = tmp_path / "src" / link
    path.rename(tmp_path / "moved")
    path.symlink_to(tmp_path / "moved")
    with pytest.raises(BadInputError, match="resolves outside the source folder"):
        import_dataset(tmp_path / "src", "idr", tmp_path / "scan")
    assert not (tmp_path / "scan").exists()


@pytest.mark.parametrize("change", [{"fl_x": -150.0}, {"fl_y": float("nan")}, {"cx": -1e6}, {"fl_x": True}])
def test_import_never_writes_negative_or_nan_intrinsics(tmp_path, change):
    write_nerfstudio(tmp_path / "src", ring_cameras(count=3))
    data = json.loads((tmp_path / "src" / "transforms.json").read_text())
    (tmp_path / "src" / "transforms.json").write_text(json.dumps({**data, **change}))
    with pytest.raises(BadInputError, match="transforms.json: (fl_x|fl_y|cx): "):
        import_dataset(tmp_path / "src", "nerfstudio", tmp_path / "scan", QUICK)
    assert not (tmp_path / "scan").exists()


def test_a_singular_idr_projection_and_a_truncated_image_are_clear_errors(tmp_path):
    write_idr(tmp_path / "src", [np.block([[c[:3, :3], 1000.0 * c[:3, 3:]], [np.array([[0, 0, 0, 1.0]])]])
                                 for c in ring_cameras(count=3)])
    arrays = dict(np.load(tmp_path / "src" / "cameras.npz"))
    np.savez(tmp_path / "src" / "cameras.npz", **{**arrays, "world_mat_1": np.zeros((4, 4))})
    with pytest.raises(BadInputError, match="world_mat_1: projection matrix is singular"):
        import_dataset(tmp_path / "src", "idr", tmp_path / "scan")
    np.savez(tmp_path / "src" / "cameras.npz", **arrays)
    image = tmp_path / "src" / "image" / "000002.png"
    image.write_bytes(image.read_bytes()[:200])
    with pytest.raises(BadInputError, match="000002.png: .*truncated or corrupt"):
        import_dataset(tmp_path / "src", "idr", tmp_path / "scan", QUICK)


def test_write_transforms_refuses_intrinsics_no_lens_has(tmp_path):
    from station.formats.transforms import PinholeCamera
    from station.process.transforms import PosedFrame, Transforms, write_transforms

    frame = PosedFrame("images/a.png", np.eye(4))
    with pytest.raises(BadInputError, match="transforms.json: fl_x: must be positive"):
        write_transforms(ScanFolder(tmp_path), Transforms(PinholeCamera(W, H, -F, F, W / 2, H / 2), [frame]))
    assert not ScanFolder(tmp_path).transforms_path.exists()
