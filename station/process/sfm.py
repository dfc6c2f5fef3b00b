"""Thin, typed wrappers over pycolmap 4.2 for the posing stage.

Turntable scans fool plain SfM (the static backdrop matches in every pair), so features are
only extracted inside the masks. Poses are expressed as OpenCV camera-to-world 4x4 matrices
everywhere outside this module; COLMAP's world-to-camera `Rigid3d` never leaks out.
COLMAP's own glog lines (several per image, and a warning per discarded partial model) are
shown only when this module's logger is at DEBUG (`station --verbose`); otherwise only its errors
pass, since each stage reports what came of them (registered views, flags).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from station.errors import BadInputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SfmSettings:
    max_features: int = 4096
    # Stones are low-contrast: COLMAP's default (0.0067) finds ~5 features on a simulated stone at
    # 320x240 and ~110 at 640x480; 0.004 roughly doubles that without admitting noise.
    peak_threshold: float = 0.004
    mask_erode_px: int = 2  # features on the silhouette edge see the backdrop: drop them
    num_threads: int = 2
    max_runtime_s: float = 600.0
    min_track_angle_deg: float = 1.5
    # Sparse rings (16 views, 20+ deg apart) leave few inliers per pair; COLMAP's defaults (15, 30)
    # drop such views. Lower floors still need a geometric verification to pass.
    min_num_matches: int = 10
    abs_pose_min_num_inliers: int = 12
    guided_matching: bool = False
    affine_sift: bool = False  # affine-adapted, domain-size-pooled SIFT: wide baselines, ~2x the time
    refine_principal_point: bool = False  # only when intrinsics are unknown and the views ring the object
    self_calibrate: bool = True  # refine focal, principal point, k1, k2, p1, p2 after posing
    calibration_loss_px: float = 1.0  # Cauchy scale of the self-calibration: mismatches weigh little
    # Distortion is only observable where features reach: tracks must span this share of the half-diagonal
    calibration_min_reach: float = 0.6
    calibration_min_gain: float = 0.05  # keep the refined lens only if it cuts the mean error by this share


@contextmanager
def colmap_log_level() -> Iterator[None]:
    """Raise COLMAP's glog threshold to ERROR for the duration, unless we log at DEBUG; restore it after."""
    previous = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = max(previous, int(pycolmap.logging.Level.ERROR))
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def write_colmap_masks(masks: dict[str, np.ndarray], folder: Path, erode_px: int) -> None:
    """COLMAP reads the mask of image `name` from `folder/name.png`; zero pixels get no features."""
    kernel = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8) if erode_px > 0 else None
    for name, mask in masks.items():
        m = mask.astype(np.uint8) * 255  # [H, W]
        if kernel is not None:
            m = cv2.erode(m, kernel)
        out = folder / f"{name}.png"
        out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out), m)


@colmap_log_level()
def extract_and_match(
    database: Path,
    image_dir: Path,
    names: list[str],
    mask_dir: Path | None,
    camera: pycolmap.Camera | None,
    settings: SfmSettings,
) -> None:
    """Masked SIFT into a fresh database, then exhaustive matching (sequential cannot close the loop)."""
    reader = pycolmap.ImageReaderOptions()
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    if camera is not None:
        reader.camera_model = camera.model.name
        reader.camera_params = ",".join(repr(float(p)) for p in camera.params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = settings.num_threads
    extraction.sift.max_num_features = settings.max_features
    extraction.sift.peak_threshold = settings.peak_threshold
    extraction.sift.estimate_affine_shape = settings.affine_sift
    extraction.sift.domain_size_pooling = settings.affine_sift
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    # The same images must give the same points (and ring gains, and training images): on more than one thread
    # COLMAP numbers images in the order their features finish, and its pair verification depends on the thread
    # order. Triangulation and bundle adjustment are reproducible on num_threads.
    number_images_by_name(database)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    matching.guided_matching = settings.guided_matching
    pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)


def number_images_by_name(database: Path) -> None:
    """Rewrite a freshly extracted `database` with its images (and their frames) numbered in name order.

    Extraction on several threads numbers them in the order their features finish, and matching and
    triangulation work in image-id order."""
    unordered = database.with_name(database.name + ".unordered")
    database.rename(unordered)
    source, target = pycolmap.Database.open(unordered), pycolmap.Database.open(database)
    try:
        for camera in source.read_all_cameras():
            target.write_camera(camera, use_camera_id=True)
        for rig in source.read_all_rigs():
            target.write_rig(rig, use_rig_id=True)
        frames = {frame.frame_id: frame for frame in source.read_all_frames()}
        number_of = {}
        for number, image in enumerate(sorted(source.read_all_images(), key=lambda image: image.name), start=1):
            (data_id,) = frames[image.frame_id].data_ids  # one camera: one image a frame
            frame = pycolmap.Frame()
            frame.frame_id, frame.rig_id = number, frames[image.frame_id].rig_id
            frame.add_data_id(pycolmap.data_t(data_id.sensor_id, number))
            target.write_frame(frame, use_frame_id=True)
            renumbered = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=number)
            renumbered.frame_id = number
            target.write_image(renumbered, use_image_id=True)
            target.write_keypoints(number, source.read_keypoints(image.image_id))
            target.write_descriptors(number, source.read_descriptors(image.image_id))
            number_of[image.image_id] = number
        for prior in source.read_all_pose_priors():  # from EXIF GPS, when the images carry it
            prior.corr_data_id = pycolmap.data_t(prior.corr_data_id.sensor_id, number_of[prior.corr_data_id.id])
            target.write_pose_prior(prior)
    finally:
        source.close()
        target.close()
    unordered.unlink()


def _rigid_from_c2w(c2w: np.ndarray) -> pycolmap.Rigid3d:
    w2c = np.linalg.inv(c2w)
    return pycolmap.Rigid3d(w2c[:3, :4])


def c2w_of(image: pycolmap.Image) -> np.ndarray:
    """OpenCV camera-to-world 4x4 of a registered COLMAP image."""
    w2c = np.eye(4)
    w2c[:3, :4] = image.cam_from_world().matrix()
    return np.linalg.inv(w2c)


def reconstruction_from_poses(database: Path, c2w_by_name: dict[str, np.ndarray]) -> pycolmap.Reconstruction:
    """A COLMAP reconstruction whose cameras sit exactly at the given poses, no points yet."""
    db = pycolmap.Database.open(database)
    try:
        cameras = db.read_all_cameras()
        rigs = db.read_all_rigs()
        frames = db.read_all_frames()
        images = db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for camera in cameras:
        rec.add_camera(camera)
    for rig in rigs:
        rec.add_rig(rig)
    image_by_id = {image.image_id: image for image in images}
    for frame in frames:
        (data_id,) = frame.data_ids
        image = image_by_id[data_id.id]
        if image.name not in c2w_by_name:
            raise BadInputError(f"{database}: image {image.name!r} has no rig pose")
        frame.rig_from_world = _rigid_from_c2w(c2w_by_name[image.name])
        rec.add_frame(frame)
        rec.add_image(image)
        rec.register_frame(frame.frame_id)
    return rec


@colmap_log_level()
def triangulate_fixed(
    rec: pycolmap.Reconstruction, database: Path, image_dir: Path, out_dir: Path, settings: SfmSettings
) -> pycolmap.Reconstruction:
    """Triangulate tracks with every camera held where the rig put it (no pose refinement)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = settings.num_threads
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.triangulation.min_angle = settings.min_track_angle_deg
    out_dir.mkdir(parents=True, exist_ok=True)
    return pycolmap.triangulate_points(rec, database, image_dir, out_dir, clear_points=True, options=options)


@dataclass(frozen=True)
class VerifiedMatches:
    """Every geometrically verified feature match of a database, as undistorted normalised camera coordinates."""

    names: list[str]  # image names; `pairs` index into it
    pairs: np.ndarray  # [P, 2] int: the two images of each verified pair
    pair_of: np.ndarray  # [M] int: each match's pair
    points: np.ndarray  # [M, 2, 2]: (x, y) / z in the pair's first and second camera, lens distortion removed
    focal_px: float  # the shared camera's focal length: a normalised distance times this is pixels


def verified_matches(database: Path) -> VerifiedMatches:
    """The inlier matches of every verified image pair (the ones SfM would build tracks from)."""
    db = pycolmap.Database.open(database)
    try:
        images = {image.image_id: image for image in db.read_all_images()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        keypoints = {image_id: db.read_keypoints(image_id)[:, :2].astype(np.float64) for image_id in images}
        normalised = {image_id: cameras[image.camera_id].cam_from_img(keypoints[image_id])
                      for image_id, image in images.items()}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    names = sorted(image.name for image in images.values())
    index = {name: k for k, name in enumerate(names)}
    pairs, pair_of, points = [], [np.zeros(0, np.int64)], [np.zeros((0, 2, 2))]
    for pair_id, geometry in zip(pair_ids, geometries):
        inliers = geometry.inlier_matches
        if len(inliers) == 0:
            continue
        first, second = pycolmap.pair_id_to_image_pair(pair_id)
        pair_of.append(np.full(len(inliers), len(pairs)))
        pairs.append((index[images[first].name], index[images[second].name]))
        points.append(np.stack([normalised[first][inliers[:, 0]], normalised[second][inliers[:, 1]]], axis=1))
    focal = float(np.mean([camera.mean_focal_length() for camera in cameras.values()])) if cameras else 1.0
    return VerifiedMatches(names, np.array(pairs, np.int64).reshape(-1, 2), np.concatenate(pair_of),
                           np.concatenate(points), focal)


@colmap_log_level()
def map_incremental(
    database: Path,
    image_dir: Path,
    out_dir: Path,
    settings: SfmSettings,
    fix_intrinsics: bool,
) -> pycolmap.Reconstruction | None:
    """Free incremental mapping (bounded in time); returns the largest model, or None."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = settings.num_threads
    options.max_runtime_seconds = int(settings.max_runtime_s)
    options.random_seed = 0
    options.min_num_matches = settings.min_num_matches
    options.mapper.abs_pose_min_num_inliers = settings.abs_pose_min_num_inliers
    if fix_intrinsics:
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
    else:
        options.ba_refine_principal_point = settings.refine_principal_point
    out_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(database, image_dir, out_dir, options=options)
    if not models:
        return None
    return max(models.values(), key=lambda rec: rec.num_reg_images())


def registered_poses(rec: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    return {image.name: c2w_of(image) for image in rec.images.values() if image.has_pose}


def points_and_colours(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points [N, 3] (float64) and their colours [N, 3] (uint8)."""
    if rec.num_points3D() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    pts = rec.points3D.values()
    xyz = np.array([p.xyz for p in pts])
    rgb = np.array([p.color for p in pts], dtype=np.uint8)
    return xyz, rgb


def self_calibrate(rec: pycolmap.Reconstruction, settings: SfmSettings,
                   hold_poses: bool) -> tuple[pycolmap.Reconstruction, str | None]:
    """Bundle-adjust the shared camera (focal, principal point, distortion) and the points on a copy.

    With `hold_poses` every view stays where the rig model put it (the rig is the prior; the lens
    alone must explain what is left); without, poses are refined too and only the gauge is fixed.
    Returns the refined model, or `rec` unchanged and why: tracks that stay near the centre cannot
    tell distortion from focal length, and a lens that does not fit better is noise fitted.
    """
    observed = [p.xy for image in rec.images.values() if image.has_pose for p in image.points2D if p.has_point3D()]
    camera = next(iter(rec.cameras.values()))
    centre = np.array([camera.principal_point_x, camera.principal_point_y])
    reach = np.percentile(np.linalg.norm(np.array(observed) - centre, axis=1), 95) / (0.5 * np.hypot(camera.width,
                                                                                                       camera.height))
    if reach < settings.calibration_min_reach:
        return rec, (f"lens not self-calibrated: features reach {100 * reach:.0f} % of the half-diagonal, "
                     f"{100 * settings.calibration_min_reach:.0f} % needed (fill more of the frame)")
    held, refined = pycolmap.Reconstruction(rec), pycolmap.Reconstruction(rec)
    _bundle_adjust_camera(held, settings, hold_poses, refine_camera=False)  # what the prior lens alone reaches
    _bundle_adjust_camera(refined, settings, hold_poses, refine_camera=True)
    before = np.concatenate(list(reprojection_errors(held).values())).mean()
    after = np.concatenate(list(reprojection_errors(refined).values())).mean()
    if after > (1.0 - settings.calibration_min_gain) * before:
        return rec, f"lens not self-calibrated: refining it moved the mean error only from {before:.3f} to {after:.3f} px"
    return refined, None


@colmap_log_level()
def _bundle_adjust_camera(rec: pycolmap.Reconstruction, settings: SfmSettings, hold_poses: bool,
                          refine_camera: bool) -> None:
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    if hold_poses:
        for frame_id in rec.reg_frame_ids():
            config.set_constant_rig_from_world_pose(frame_id)
    else:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = refine_camera
    options.refine_principal_point = refine_camera
    options.refine_extra_params = refine_camera
    options.refine_rig_from_world = not hold_poses
    options.refine_sensor_from_rig = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = settings.calibration_loss_px
    options.ceres.solver_options.num_threads = settings.num_threads
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()


def reprojection_errors(rec: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    """Per registered image, the pixel distance of each observation from its 3D point's projection."""
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        seen = [p for p in image.points2D if p.has_point3D()]
        if not seen:
            out[image.name] = np.zeros(0)
            continue
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in seen])
        cam = xyz @ image.cam_from_world().rotation.matrix().T + image.cam_from_world().translation
        projected = rec.cameras[image.camera_id].img_from_cam(cam, check_cheirality=False)
        out[image.name] = np.linalg.norm(projected - np.array([p.xy for p in seen]), axis=1)
    return out
