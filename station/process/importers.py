"""`station import`: bring a posed dataset from elsewhere into a scan folder at the posed stage.

Readers are pure functions from a source folder to a `SourceDataset` in one convention (OpenCV
camera-to-world, source units); `import_dataset` then converts units and axes explicitly and
writes images/, masks/ and poses/ exactly as `pose_scan` would, so training, the gate and the
report cannot tell an imported scan from one of ours. Sources are untrusted: every path they
name must stay inside the source folder.

Conventions read:
- nerfstudio / NeRF-synthetic `transforms.json`: c2w in OpenGL axes; `fl_x`.. or `camera_angle_x`.
- COLMAP model (cameras/images/points3D, .bin or .txt): world-to-camera, OpenCV axes.
- IDR/NeuS (DTU): `cameras.npz` with `world_mat_i` = K [R|t] (P, world-to-image, DTU world in mm)
  and `scale_mat_i` (unit sphere -> world); images in `image/`, masks in `mask/`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pycolmap
from PIL import Image

from station.errors import BadInputError
from station.process.colmap_export import colmap_model, write_colmap_model
from station.process.lens import Lens, lens_from_colmap, lens_from_nerfstudio, undistortion
from station.process.poses import write_point_ply
from station.process.rig_model import apply_similarity
from station.process.sfm import Intrinsics
from station.process.transforms import MAX_FRAMES, PosedFrame, Transforms, opengl_to_opencv, write_transforms
from station.process.visual_hull import carve, ring_frame
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with

Format = Literal["nerfstudio", "colmap", "idr"]
Orient = Literal["auto", "keep", "ring"]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEFAULT_UNITS_TO_M = {"nerfstudio": 1.0, "colmap": 1.0, "idr": 0.001}  # DTU's world is in millimetres


@dataclass(frozen=True)
class ImportSettings:
    units_to_m: float | None = None  # None: the format's default (DTU mm -> m; others assumed metres)
    orient: Orient = "auto"  # keep source axes, or "ring": z along the camera ring's normal, cameras above
    hull_resolution: int = 96


@dataclass
class SourceFrame:
    image: Path
    mask: Path | None  # a mask file, or None (alpha channel or nothing)
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world, source units


@dataclass
class SourceDataset:
    intrinsics: Intrinsics
    frames: list[SourceFrame]
    points: tuple[np.ndarray, np.ndarray] | None = None  # xyz [N, 3] source units, rgb [N, 3] uint8
    lens: Lens | None = None  # the source camera's distortion, undistorted on import; None: pinhole


@dataclass
class ImportReport:
    format: str
    frames: int
    masks: str  # "files", "alpha", or "none"
    units_to_m: float
    orient: str
    init_cloud: str  # "source", "visual_hull", or "none"
    points: int
    flags: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


def _inside(root: ScanFolder, rel: str, where: str) -> Path:
    try:
        return root.resolve_inside(rel)
    except BadInputError as exc:
        raise BadInputError(f"{where}: {exc}") from exc


def _finite(data: dict, key: str, where: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise BadInputError(f"{where}: field {key!r} must be a positive number, got {value!r}")
    return float(value)


def _find_image(path: Path, where: str) -> Path:
    """nerfstudio names files with their suffix; NeRF-synthetic leaves it off ('./train/r_0')."""
    if path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES:
        if path.with_name(path.name + suffix).is_file():
            return path.with_name(path.name + suffix)
    raise BadInputError(f"{where}: image {path} not found")


def read_nerfstudio(src: Path) -> SourceDataset:
    """transforms.json (nerfstudio) or transforms_train.json (NeRF-synthetic) in `src`."""
    root = ScanFolder(src)
    path = next((src / n for n in ("transforms.json", "transforms_train.json") if (src / n).is_file()), None)
    if path is None:
        raise BadInputError(f"{src}: no transforms.json or transforms_train.json")
    data = root.read_json(path)
    where = str(path)
    frames_raw = data.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw or len(frames_raw) > MAX_FRAMES:
        raise BadInputError(f"{where}: field 'frames' must be a list of 1..{MAX_FRAMES} frames")
    frames = []
    for i, raw in enumerate(frames_raw):
        fwhere = f"{where}: frames[{i}]"
        if not isinstance(raw, dict) or not isinstance(raw.get("file_path"), str):
            raise BadInputError(f"{fwhere}: needs a string 'file_path'")
        image = _find_image(_inside(root, raw["file_path"], f"{fwhere}.file_path"), f"{fwhere}.file_path")
        mask = None
        if raw.get("mask_path") is not None:
            mask = _inside(root, str(raw["mask_path"]), f"{fwhere}.mask_path")
            if not mask.is_file():
                raise BadInputError(f"{fwhere}.mask_path: {mask} not found")
        try:
            gl = np.asarray(raw.get("transform_matrix"), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise BadInputError(f"{fwhere}.transform_matrix: not numeric ({exc})") from exc
        if gl.shape not in ((4, 4), (3, 4)) or not np.isfinite(gl).all():
            raise BadInputError(f"{fwhere}.transform_matrix: must be a finite 4x4 matrix, got shape {gl.shape}")
        c2w = np.eye(4)
        c2w[:3, :4] = gl[:3, :4]
        frames.append(SourceFrame(image, mask, opengl_to_opencv(c2w)))
    with Image.open(frames[0].image) as img:
        width, height = img.size
    if "fl_x" in data or "camera_angle_x" not in data:
        w, h = int(data.get("w", width)), int(data.get("h", height))
        fx = _finite(data, "fl_x", where)
        fy = float(data.get("fl_y", fx))
        intr = Intrinsics(w, h, fx, fy, float(data.get("cx", w / 2.0)), float(data.get("cy", h / 2.0)))
    else:
        # NeRF-synthetic: horizontal field of view only, principal point at the centre.
        fx = 0.5 * width / np.tan(0.5 * _finite(data, "camera_angle_x", where))
        intr = Intrinsics(width, height, fx, fx, width / 2.0, height / 2.0)
    return SourceDataset(intr, frames, lens=lens_from_nerfstudio(data, intr, where))


def _colmap_dirs(src: Path) -> tuple[Path, Path]:
    for model in (src, src / "sparse" / "0", src / "sparse", src / "colmap"):
        if any((model / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            for images in (src / "images", model.parent / "images", model.parent.parent / "images"):
                if images.is_dir():
                    return model, images
            raise BadInputError(f"{src}: COLMAP model found in {model} but no images/ folder beside it")
    raise BadInputError(f"{src}: no COLMAP model (cameras.bin/.txt) in ., sparse/0, sparse or colmap")


def read_colmap(src: Path) -> SourceDataset:
    model_dir, image_dir = _colmap_dirs(src)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (RuntimeError, ValueError) as exc:
        raise BadInputError(f"{model_dir}: unreadable COLMAP model ({exc})") from exc
    if rec.num_cameras() != 1:
        raise BadInputError(f"{model_dir}: {rec.num_cameras()} cameras; one shared camera is supported")
    lens = lens_from_colmap(next(iter(rec.cameras.values())), str(model_dir))
    intr = lens.intrinsics
    root = ScanFolder(image_dir)
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        path = _inside(root, image.name, f"{model_dir}: image {image.name!r}")
        if not path.is_file():
            raise BadInputError(f"{model_dir}: image {image.name!r} not found in {image_dir}")
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        frames.append(SourceFrame(path, None, np.linalg.inv(w2c)))
    if not frames:
        raise BadInputError(f"{model_dir}: no registered images")
    points = None
    if rec.num_points3D():
        pts = list(rec.points3D.values())
        points = (np.array([p.xyz for p in pts]), np.array([p.color for p in pts], dtype=np.uint8))
    return SourceDataset(intr, frames, points, lens)


def read_idr(src: Path) -> SourceDataset:
    """IDR/NeuS layout: cameras.npz (or cameras_sphere.npz), image/, optional mask/."""
    npz = next((src / n for n in ("cameras.npz", "cameras_sphere.npz") if (src / n).is_file()), None)
    if npz is None:
        raise BadInputError(f"{src}: no cameras.npz or cameras_sphere.npz")
    images = sorted(p for p in (src / "image").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise BadInputError(f"{src / 'image'}: no images")
    masks = sorted(p for p in (src / "mask").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if masks and len(masks) != len(images):
        raise BadInputError(f"{src / 'mask'}: {len(masks)} masks for {len(images)} images")
    try:
        cams = dict(np.load(npz, allow_pickle=False))
    except (OSError, ValueError) as exc:
        raise BadInputError(f"{npz}: unreadable ({exc})") from exc
    frames, ks = [], []
    for i, image in enumerate(images):
        key = f"world_mat_{i}"
        if key not in cams or np.shape(cams[key]) not in ((4, 4), (3, 4)):
            raise BadInputError(f"{npz}: missing or malformed {key!r} for {image.name}")
        # P = K [R | t]; OpenCV splits it into K, R (world-to-camera) and the homogeneous centre.
        k, r, centre = cv2.decomposeProjectionMatrix(np.asarray(cams[key], dtype=np.float64)[:3, :4])[:3]
        k = k / k[2, 2]
        c2w = np.eye(4)
        c2w[:3, :3] = r.T
        c2w[:3, 3] = centre[:3, 0] / centre[3, 0]
        frames.append(SourceFrame(image, masks[i] if masks else None, c2w))
        ks.append(k)
    k = np.mean(ks, axis=0)
    if np.abs(np.array(ks) - k).max() > 1e-3 * k[0, 0]:
        raise BadInputError(f"{npz}: intrinsics differ between views; one shared camera is supported")
    with Image.open(images[0]) as img:
        width, height = img.size
    return SourceDataset(Intrinsics(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2]), frames)


READERS = {"nerfstudio": read_nerfstudio, "colmap": read_colmap, "idr": read_idr}


def import_dataset(src: Path, fmt: Format, out: Path, settings: ImportSettings | None = None) -> ImportReport:
    """Read `src` in format `fmt`, convert to metres and station axes, and write scan folder `out`."""
    started = time.monotonic()
    settings = settings or ImportSettings()
    if fmt not in READERS:
        raise BadInputError(f"import: unknown format {fmt!r} (choose from {', '.join(READERS)})")
    src = Path(src).resolve()
    if not src.is_dir():
        raise BadInputError(f"import: source {src} is not a folder")
    data = READERS[fmt](src)
    units = settings.units_to_m if settings.units_to_m is not None else DEFAULT_UNITS_TO_M[fmt]
    if not units > 0:
        raise BadInputError(f"import: units_to_m must be positive, got {units}")
    orient = {"nerfstudio": "keep", "colmap": "ring", "idr": "ring"}[fmt] if settings.orient == "auto" else settings.orient
    rot, origin = np.eye(3), np.zeros(3)
    if orient == "ring":
        rot, origin = ring_frame([f.c2w for f in data.frames])
    # x -> units * R (x - origin): metres, station axes.
    def convert(c2w: np.ndarray) -> np.ndarray:
        return apply_similarity(c2w, units, rot, -units * rot @ origin)

    scan = ScanFolder(out)
    flags: list[str] = []
    undistort = undistortion(data.lens) if data.lens is not None else None
    intrinsics = undistort.target if undistort is not None else data.intrinsics
    frames, masks, images, mask_kind = [], [], [], "none"
    for i, frame in enumerate(data.frames):
        name = f"{i:04d}_{frame.image.stem}.png"
        with Image.open(frame.image) as img:
            if img.size != (data.intrinsics.width, data.intrinsics.height):
                raise BadInputError(f"{frame.image}: size {img.size} differs from the camera's "
                                    f"{data.intrinsics.width}x{data.intrinsics.height}")
            rgba = img.convert("RGBA") if img.mode in ("RGBA", "LA", "PA") else None
            rgb = np.asarray(img.convert("RGB"))  # [H, W, 3]
        # kept as given: 255 is object, a value between is its coverage (an alpha channel is straight alpha,
        # so the RGB already holds the object's own colour there, the form our masks and images take too)
        coverage = None
        if frame.mask is not None:
            with Image.open(frame.mask) as m:
                if m.size != img.size:
                    raise BadInputError(f"{frame.mask}: mask size {m.size} differs from its image's {img.size}")
                coverage = np.asarray(m.convert("L"))
            mask_kind = "files"
        elif rgba is not None:
            coverage = np.asarray(rgba)[:, :, 3]
            mask_kind = "alpha"
        if undistort is not None:
            rgb = undistort.image(rgb)
            coverage = None if coverage is None else undistort.mask(coverage)
        atomic_write_with(scan.images_dir / name, lambda tmp, a=rgb: Image.fromarray(a).save(tmp, format="PNG"))
        if coverage is not None:
            atomic_write_with(scan.masks_dir / name, lambda tmp, m=coverage: Image.fromarray(m).save(tmp, format="PNG"))
            masks.append(coverage > 127)
        images.append(rgb)
        frames.append(PosedFrame(f"images/{name}", convert(frame.c2w), f"masks/{name}" if coverage is not None else None))
    if 0 < len(masks) < len(frames):
        raise BadInputError(f"{src}: {len(masks)} of {len(frames)} frames have a mask; all or none are needed")

    ply, init, count = None, "none", 0
    if data.points is not None and len(data.points[0]):
        xyz = units * (data.points[0] - origin) @ rot.T
        rgb_pts, init = data.points[1], "source"
    elif masks:
        xyz, rgb_pts = carve([f.c2w for f in frames], masks, images, intrinsics, settings.hull_resolution)
        init = "visual_hull"
    else:
        xyz, rgb_pts = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        flags.append("no points and no masks: no starting cloud")
    if len(xyz):
        atomic_write_with(scan.poses_dir / "points3d.ply", lambda tmp: write_point_ply(tmp, xyz, rgb_pts))
        ply, count = "poses/points3d.ply", len(xyz)
    write_transforms(scan, Transforms(intrinsics, frames, ply))
    write_colmap_model(scan, colmap_model(Transforms(intrinsics, frames, ply), (xyz, rgb_pts)))
    if not scan.scan_json.exists():
        atomic_write_json(scan.scan_json, {"stone_id": src.name, "imported": {"format": fmt, "source": str(src)}})
    if undistort is not None:
        flags.append(f"{data.lens.model} lens {data.lens.named()} undistorted on import to a pinhole camera")
    if orient == "ring":
        flags.append("axes from the camera ring: origin is where the cameras look, not the plate surface")
    report = ImportReport(fmt, len(frames), mask_kind, units, orient, init, count, flags,
                          time.monotonic() - started)
    atomic_write_json(scan.poses_dir / "report.json", report.to_dict())
    return report

