"""Posing a scan: rig poses held fixed + triangulation and a drift check against the matches, or pure SfM.

With a rig model the poses are known; SfM only adds a metric point cloud (triangulated with
the cameras fixed) and a check that the scan matches the rig (each elevation ring, refitted to
the feature matches, must stay put: `drift`). Without one (scans from elsewhere) incremental
SfM poses the views and the ring of cameras fixes up, origin and, when scan.json has a rig,
scale. Too few points (a textureless stone) falls back to a visual hull carved from the masks,
with a flag.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from station.errors import BadInputError, ScanFolderError, StationError
from station.formats.transforms import PinholeCamera
from station.process import sfm
from station.process.colmap_export import colmap_model, write_colmap_model
from station.process.drift import DriftLimits, check_rig
from station.process.images_io import read_exr, read_png16, write_exr_half, write_png16
from station.process.lens import Lens, Undistortion, displacement_px, lens_from_colmap, undistortion
from station.process.photometry import ring_gains
from station.process.rig_model import PosedView, RigModel, calibrate_rig
from station.process.transforms import PosedFrame, Transforms, read_transforms, write_transforms
from station.process.visual_hull import carve, ring_frame
from station.process.workers import map_in_threads
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with


class PosingError(StationError):
    """The scan cannot be posed (no usable images, SfM registered too few views)."""

    exit_code = 2


@dataclass(frozen=True)
class PoseSettings:
    sfm: sfm.SfmSettings = field(default_factory=sfm.SfmSettings)
    min_points: int = 200  # fewer triangulated points than this: carve a visual hull instead
    cross_check: bool = True
    drift: DriftLimits = field(default_factory=DriftLimits)
    hull_resolution: int = 96
    # Foreign scans have no rig to lean on and often sparse views: pay for affine SIFT there, where it
    # lowers the worst camera error.
    fallback_affine_sift: bool = True
    min_undistort_px: float = 0.1  # distortion moving no border pixel further than this is left in (no resample)
    normalise_exposure: bool = True  # bring every ring to one exposure by the stone points they share
    min_exposure_change: float = 0.005  # a ring gain closer to 1 than this is left alone (no re-encode)


@dataclass
class PoseReport:
    method: str  # "rig" or "sfm"
    views: int
    planned_views: int
    registered: list[str]
    unregistered: list[str]
    points: int
    init_cloud: str  # "sfm" or "visual_hull"
    reprojection_error_px: float
    mean_track_length: float
    cross_check: dict = field(default_factory=dict)
    reprojection_by_ring_px: dict[str, float] = field(default_factory=dict)  # elevation (or "all") -> mean error
    lens: dict = field(default_factory=dict)  # the self-calibrated camera of the developed images, and its fate
    ring_gains: dict[str, float] = field(default_factory=dict)  # elevation -> exposure gain applied to its images
    flags: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FrameRef:
    name: str  # file name inside images/
    mask_name: str | None  # file name inside masks/, when a mask exists
    elevation_deg: float | None
    azimuth_deg: float | None


def collect_frames(scan: ScanFolder) -> tuple[list[FrameRef], int]:
    """The developed images to pose (from the manifest's shots when present) and how many were planned."""
    shots = [e for e in scan.read_manifest() if e.kind == "shot"]
    if shots:
        refs = []
        for entry in shots:
            name = Path(entry.file).stem + ".png"
            if (scan.images_dir / name).is_file():
                mask = name if (scan.masks_dir / name).is_file() else None
                refs.append(FrameRef(name, mask, entry.elevation_deg, entry.azimuth_deg))
        return refs, len(shots)
    if not scan.images_dir.is_dir():
        raise ScanFolderError(f"{scan.images_dir}: missing (develop the scan first)")
    names = sorted(p.name for p in scan.images_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    refs = [FrameRef(n, n if (scan.masks_dir / n).is_file() else None, None, None) for n in names]
    return refs, len(refs)


def _image_size(scan: ScanFolder, refs: list[FrameRef]) -> tuple[int, int]:
    sizes = set()
    for ref in refs:
        try:
            with Image.open(scan.resolve_inside(f"images/{ref.name}")) as img:
                sizes.add(img.size)
        except OSError as exc:
            raise ScanFolderError(f"{scan.images_dir / ref.name}: unreadable image ({exc})") from exc
    if len(sizes) != 1:
        raise ScanFolderError(f"{scan.images_dir}: images differ in size {sorted(sizes)}")
    return sizes.pop()


def _load_mask(scan: ScanFolder, name: str) -> np.ndarray:
    with Image.open(scan.resolve_inside(f"masks/{name}")) as img:
        return np.asarray(img.convert("L")) > 127  # [H, W]


def _scan_rig(scan: ScanFolder) -> RigGeometry | None:
    if not scan.scan_json.exists():
        return None
    rig = scan.read_scan_json().get("rig")
    return RigGeometry.from_dict(rig) if isinstance(rig, dict) else None


def pose_scan(scan: ScanFolder, settings: PoseSettings, rig: RigModel | None) -> PoseReport:
    """Pose every developed image of `scan` and write poses/ (COLMAP model, transforms.json, cloud, report)."""
    started = time.monotonic()
    refs, planned = collect_frames(scan)
    if len(refs) < 3:
        raise PosingError(f"{scan.images_dir}: {len(refs)} usable images, at least 3 are needed to pose")
    width, height = _image_size(scan, refs)
    flags = []
    if len(refs) < planned:
        flags.append(f"fewer images than planned: {len(refs)} of {planned}")
    masks = {r.name: _load_mask(scan, r.mask_name) for r in refs if r.mask_name is not None}
    if len(masks) < len(refs):
        flags.append(f"{len(refs) - len(masks)} images have no mask: features may land on the backdrop")
    use_rig = rig is not None and all(r.elevation_deg is not None for r in refs)
    if rig is not None and not use_rig:
        flags.append("rig model given but the scan has no manifest angles: pure SfM used")

    work = Path(tempfile.mkdtemp(prefix="station-poses-"))
    try:
        database = work / "database.db"
        mask_dir = None
        if masks:
            mask_dir = work / "masks"
            sfm.write_colmap_masks(masks, mask_dir, settings.sfm.mask_erode_px)
        names = [r.name for r in refs]
        calibrate = settings.sfm.self_calibrate
        note: str | None = "lens held: self-calibration off" if not calibrate else "lens held: no SfM points"
        if use_rig:
            prior = rig.lens().scaled(width, height)
            camera = (prior.refinable() if calibrate else prior).to_colmap(keep_model=True)
            rig_poses = {r.name: rig.camera_to_world(r.elevation_deg, r.azimuth_deg) for r in refs}
            sfm.extract_and_match(database, scan.images_dir, names, mask_dir, camera, settings.sfm)
            rec = sfm.reconstruction_from_poses(database, rig_poses)
            rec = sfm.triangulate_fixed(rec, database, scan.images_dir, work / "triangulated", settings.sfm)
            if calibrate and rec.num_points3D():
                rec, note = sfm.self_calibrate(rec, settings.sfm, hold_poses=True)
            poses = rig_poses
            report = PoseReport("rig", len(refs), planned, sorted(poses), [], 0, "sfm", 0.0, 0.0, flags=flags)
            if settings.cross_check:
                report.cross_check = check_rig(sfm.verified_matches(database), rig_poses,
                                               {r.name: r.elevation_deg for r in refs}, rig.orbit_radius(),
                                               settings.drift)
                flags.extend(report.cross_check.pop("flags"))
        else:
            scan_rig = _scan_rig(scan)
            camera = None
            if scan_rig is not None:
                k = scan_rig.scaled(width, height).intrinsics()
                prior = Lens(PinholeCamera(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
                camera = (prior.refinable() if calibrate else prior).to_colmap(keep_model=True)
            fallback = replace(settings.sfm, affine_sift=settings.fallback_affine_sift, refine_principal_point=True)
            sfm.extract_and_match(database, scan.images_dir, names, mask_dir, camera, fallback)
            rec = sfm.map_incremental(database, scan.images_dir, work / "mapped", fallback, camera is not None)
            if rec is None or rec.num_reg_images() < 3:
                raise PosingError(f"{scan.root}: SfM registered {0 if rec is None else rec.num_reg_images()} views")
            if calibrate and rec.num_points3D():
                rec, note = sfm.self_calibrate(rec, settings.sfm, hold_poses=False)
            rec, scaled = _turntable_gauge(rec, scan_rig)
            if not scaled:
                flags.append("no rig in scan.json: scale is SfM units, not metres")
            poses = sfm.registered_poses(rec)
            missing = [n for n in names if n not in poses]
            if missing:
                flags.append(f"SfM registered {len(poses)} of {len(names)} views; dropped: {', '.join(missing)}")
            report = PoseReport("sfm", len(refs), planned, sorted(poses), missing, 0, "sfm", 0.0, 0.0, flags=flags)
        report.reprojection_error_px = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else 0.0
        report.mean_track_length = float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0
        report.reprojection_by_ring_px = _ring_errors(rec, refs)
        if settings.normalise_exposure and rec.num_points3D() and all(r.elevation_deg is not None for r in refs):
            report.ring_gains = _normalise_ring_exposure(scan, rec, refs, settings.min_exposure_change)
        lens, undistort = _lens_of(rec, settings, flags)
        report.lens = {"intrinsics": vars(lens.intrinsics), **lens.to_dict(), "max_shift_px": displacement_px(lens),
                       "undistorted": undistort is not None, "self_calibration": note or "refined"}
        intr = undistort.target if undistort is not None else lens.intrinsics
        if undistort is not None:
            _undistort_scan(scan, undistort)
            masks = {name: undistort.mask(m) for name, m in masks.items()}
        xyz, rgb = sfm.points_and_colours(rec)
        if len(xyz) < settings.min_points:
            if len(masks) == len(refs):
                posed = [r for r in refs if r.name in poses]
                images = [np.asarray(Image.open(scan.images_dir / r.name).convert("RGB")) for r in posed]
                xyz, rgb = carve([poses[r.name] for r in posed], [masks[r.name] for r in posed], images, intr,
                                 settings.hull_resolution)
                report.init_cloud = "visual_hull"
                flags.append(f"only {rec.num_points3D()} SfM points (textureless?): starting cloud carved from masks")
            else:
                flags.append(f"only {rec.num_points3D()} SfM points and no masks to carve a hull: sparse start")
        report.points = len(xyz)
        _write_outputs(scan, rec if report.init_cloud == "sfm" else None, lens, refs, poses, intr, xyz, rgb)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report.seconds = time.monotonic() - started
    atomic_write_json(scan.poses_dir / "report.json", report.to_dict())
    return report


def _ring_errors(rec: pycolmap.Reconstruction, refs: list[FrameRef]) -> dict[str, float]:
    """Mean reprojection error per elevation ring: a ring the shared lens fits worse points at a moved camera."""
    errors = sfm.reprojection_errors(rec)
    rings: dict[str, list[np.ndarray]] = {}
    for ref in refs:
        if ref.name in errors:
            rings.setdefault("all" if ref.elevation_deg is None else f"{ref.elevation_deg:g}", []).append(errors[ref.name])
    return {ring: float(np.concatenate(e).mean()) for ring, e in rings.items() if sum(map(len, e))}


def _normalise_ring_exposure(scan: ScanFolder, rec: pycolmap.Reconstruction, refs: list[FrameRef],
                             min_change: float) -> dict[str, float]:
    """Scale each ring's images (and its linear EXRs, plates too) by the gain its shared stone points ask for.

    The develop already matched each shot to its ring's plate; what is left is one exposure error per plate.
    """
    ring_of = {r.name: f"{r.elevation_deg:g}" for r in refs}
    azimuth_of = {r.name: float(r.azimuth_deg) for r in refs}
    tracked = [(image.name, [(p.point3D_id, p.xy) for p in image.points2D if p.has_point3D()])
               for image in rec.images.values() if image.has_pose and image.name in ring_of]

    def observe(name_points: tuple[str, list]) -> list[tuple[int, str, float, float]]:
        name, points = name_points
        box = cv2.blur(read_png16(scan.images_dir / name).mean(axis=2), (3, 3))  # [H, W] luminance
        seen = []
        for point_id, xy in points:
            x, y = (min(max(int(v), 0), n - 1) for v, n in zip(xy, box.shape[::-1]))
            if box[y, x] > 1e-3:
                seen.append((point_id, ring_of[name], azimuth_of[name], float(np.log(box[y, x]))))
        return seen

    observations = [o for seen in map_in_threads(observe, tracked) for o in seen]
    gains = {ring: gain if abs(gain - 1.0) > min_change else 1.0 for ring, gain in ring_gains(observations).items()}
    rescale = [(scan.images_dir / ref.name, gains.get(ring_of[ref.name], 1.0)) for ref in refs]
    rescale += [(scan.images_linear_dir / f"{Path(entry.file).stem}.exr", gains.get(f"{entry.elevation_deg:g}", 1.0))
                for entry in scan.read_manifest()]

    def rewrite(path_gain: tuple[Path, float]) -> None:
        path, gain = path_gain
        if path.suffix == ".png":
            write_png16(path, read_png16(path) * np.float32(gain))
        elif path.is_file():
            write_exr_half(path, read_exr(path) * np.float32(gain))

    map_in_threads(rewrite, [(path, gain) for path, gain in rescale if gain != 1.0])
    return gains


def _lens_of(rec: pycolmap.Reconstruction, settings: PoseSettings, flags: list[str]) -> tuple[Lens, Undistortion | None]:
    """The shared camera as posed, and the remap to a pinhole when its distortion is worth one."""
    camera = next(iter(rec.cameras.values()))
    try:
        lens = lens_from_colmap(camera, "self-calibration")
    except BadInputError as exc:
        flags.append(f"{exc}: distortion ignored")
        k = camera.calibration_matrix()
        return Lens(PinholeCamera(camera.width, camera.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])), None
    return lens, undistortion(lens, settings.min_undistort_px)


def _undistort_scan(scan: ScanFolder, undistort: Undistortion) -> None:
    """Undistort, once and in place, every developed image, mask and linear EXR (plates too): what training
    and the mask re-cut read then all share the pinhole camera."""
    def rewrite(path: Path) -> None:
        if path.suffix == ".exr":
            write_exr_half(path, undistort.image(read_exr(path)))
            return
        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if data is None:
            raise ScanFolderError(f"{path}: unreadable image")
        _rewrite_png(path, undistort.mask(data) if path.parent == scan.masks_dir else undistort.image(data))

    exrs = sorted(scan.images_linear_dir.glob("*.exr")) if scan.images_linear_dir.is_dir() else []
    map_in_threads(rewrite, sorted(scan.images_dir.glob("*.png")) + sorted(scan.masks_dir.glob("*.png")) + exrs)


def _rewrite_png(path: Path, data: np.ndarray) -> None:
    def writer(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), data):
            raise OSError(f"{path}: OpenCV could not write the undistorted image")

    atomic_write_with(path, writer)


def _turntable_gauge(rec: pycolmap.Reconstruction, rig: RigGeometry | None) -> tuple[pycolmap.Reconstruction, bool]:
    """Put a free SfM model into a turntable-like frame: z along the camera ring's normal, cameras above.

    With the scan's rig geometry the cameras' distance to where they look is the arm length and that
    point sits at the aim height, which fixes scale and the plate-surface origin; without it the
    origin is the look-at point and the scale stays SfM units.
    """
    poses = list(sfm.registered_poses(rec).values())
    centres = np.array([p[:3, 3] for p in poses])
    rot, target = ring_frame(poses)
    scale, lift = 1.0, 0.0
    if rig is not None:
        scale = rig.orbit_radius_m / float(np.mean(np.linalg.norm(centres - target, axis=1)))
        lift = rig.aim_height_m
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(rot), -scale * rot @ target + np.array([0, 0, lift])))
    return rec, rig is not None


def _write_outputs(scan: ScanFolder, tracks: pycolmap.Reconstruction | None, lens: Lens, refs: list[FrameRef],
                   poses: dict[str, np.ndarray], intr: PinholeCamera, xyz: np.ndarray, rgb: np.ndarray) -> None:
    atomic_write_with(scan.poses_dir / "points3d.ply", lambda tmp: write_point_ply(tmp, xyz, rgb))
    frames = [PosedFrame(f"images/{r.name}", poses[r.name], f"masks/{r.mask_name}" if r.mask_name else None)
              for r in refs if r.name in poses]
    transforms = Transforms(intr, frames, "poses/points3d.ply")
    write_transforms(scan, transforms)
    write_colmap_model(scan, colmap_model(transforms, (xyz, rgb), tracks, lens))


def write_point_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with float xyz and uchar colours (what nerfstudio's ply init reads)."""
    vertex = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(vertex.tobytes())


def calibrate_from_scan(scan: ScanFolder, settings: PoseSettings, nominal: RigModel) -> tuple[RigModel, PoseReport]:
    """Calibrate the station's rig model from one full scan: pure SfM, then fit axis and elevations.

    Writes the scan's poses/ from the free SfM run (they are that scan's best poses anyway).
    """
    refs, _ = collect_frames(scan)
    if any(r.elevation_deg is None for r in refs):
        raise PosingError(f"{scan.root}: rig calibration needs the manifest's elevation and azimuth per frame")
    report = pose_scan(scan, settings, None)
    by_name = {r.name: r for r in refs}
    views = [PosedView(by_name[Path(f.file_path).name].elevation_deg, by_name[Path(f.file_path).name].azimuth_deg,
                       f.c2w) for f in read_transforms(scan).frames]
    lens = Lens.from_dict(PinholeCamera(**report.lens["intrinsics"]), report.lens, f"{scan.poses_dir}: lens")
    return calibrate_rig(views, nominal, lens if settings.sfm.self_calibrate else None), report
