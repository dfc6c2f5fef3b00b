"""`station import`: bring a posed dataset from elsewhere into a scan folder at the posed stage.

Readers are pure functions from a source folder to a `SourceDataset` in one convention (OpenCV
camera-to-world, source units); `import_dataset` then converts units and axes explicitly and
writes images/, masks/ and poses/ exactly as `pose_scan` would, so training, the gate and the
report cannot tell an imported scan from one of ours. Sources are untrusted: every path they
name or hold, symlinks resolved, must stay inside the source folder (no parent folder is searched),
and images are size-checked from their headers before decoding.

Conventions read:
- nerfstudio / NeRF-synthetic `transforms.json`: c2w in OpenGL axes; `fl_x`.. or `camera_angle_x`.
- COLMAP model (cameras/images/points3D, .bin or .txt): world-to-camera, OpenCV axes.
- IDR/NeuS (DTU): `cameras.npz` with `world_mat_i` = K [R|t] (P, world-to-image, DTU world in mm)
  and `scale_mat_i` (unit sphere -> world); images in `image/`, masks in `mask/`.
- Middlebury multi-view (Seitz et al.): one `<set>_par.txt`, K [R | t] per image, world-to-camera,
  OpenCV axes, metres; images beside it; no masks (`masks="dark-backdrop"` derives them).
Distorted cameras (nerfstudio OPENCV/OPENCV_FISHEYE, COLMAP's radial and OpenCV models) are undistorted
on import, masks alike (`lens.py`), and the pinhole that results is what transforms.json holds.
"""

from __future__ import annotations

import math
import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, get_args

import cv2
import numpy as np
import pycolmap
from PIL import Image

from station.errors import BadInputError, FormatError, ScanFolderError
from station.formats.colmap import check_colmap_binary
from station.formats.images import DEFAULT_LIMITS, ImageLimits, checked_size, open_pil
from station.formats.jsonfile import read_json_object
from station.formats.middlebury import parse_par, shared_k
from station.formats.transforms import (CameraFields, NerfTransforms, PinholeCamera, check_camera, check_rotation,
                                        parse_transforms, pinhole)
from station.process.backdrop_masks import dark_backdrop_mask
from station.process.colmap_export import colmap_model, write_colmap_model
from station.process.lens import Lens, lens_from_colmap, lens_from_nerfstudio, split_nerfstudio_lens, undistortion
from station.process.poses import write_point_ply
from station.process.rig_model import apply_similarity
from station.process.transforms import PosedFrame, Transforms, opengl_to_opencv, write_transforms
from station.process.visual_hull import carve, ring_frame
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with

Format = Literal["nerfstudio", "colmap", "idr", "middlebury"]
Orient = Literal["auto", "keep", "ring"]
MaskSource = Literal["none", "dark-backdrop"]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEFAULT_UNITS_TO_M = {"nerfstudio": 1.0, "colmap": 1.0, "idr": 0.001, "middlebury": 1.0}  # DTU's world is in mm
DEFAULT_ORIENT = {"nerfstudio": "keep", "colmap": "ring", "idr": "ring", "middlebury": "ring"}


@dataclass(frozen=True)
class ImportSettings:
    units_to_m: float | None = None  # None: the format's default (DTU mm -> m; others assumed metres)
    orient: Orient = "auto"  # keep source axes, or "ring": z along the camera ring's normal, cameras above
    hull_resolution: int = 96
    image_limits: ImageLimits = DEFAULT_LIMITS  # the largest source image decoded
    masks: MaskSource = "none"  # for frames the source gives no mask: leave them unmasked, or derive one


@dataclass
class SourceFrame:
    image: Path
    mask: Path | None  # a mask file, or None (alpha channel or nothing)
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world, source units


@dataclass
class SourceDataset:
    intrinsics: PinholeCamera
    frames: list[SourceFrame]
    points: tuple[np.ndarray, np.ndarray] | None = None  # xyz [N, 3] source units, rgb [N, 3] uint8
    lens: Lens | None = None  # the source camera's distortion, undistorted on import; None: pinhole


@dataclass
class ImportReport:
    format: str
    frames: int
    masks: str  # "files", "alpha", "dark-backdrop" (derived on import), or "none"
    units_to_m: float
    orient: str
    init_cloud: str  # "source", "visual_hull", or "none"
    points: int
    flags: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


def _inside(root: ScanFolder, rel: str | Path, source: object, field: str | None) -> Path:
    """`rel` resolved (symlinks followed) and refused unless it stays inside the source folder."""
    try:
        return root.resolve_inside(rel)
    except ScanFolderError as exc:
        raise FormatError(source, field, f"{str(rel)!r} resolves outside the source folder {root.root}") from exc


def _listed_images(root: ScanFolder, folder: str) -> list[Path]:
    """Image files in `folder` of the source, each resolved inside it (a symlink out is refused, not read)."""
    directory = _inside(root, folder, root.root, folder)
    if not directory.is_dir():
        return []
    return sorted(_inside(root, p, directory, p.name) for p in directory.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _find_image(root: ScanFolder, rel: str, source: object, field: str) -> Path:
    """nerfstudio names files with their suffix; NeRF-synthetic leaves it off ('./train/r_0')."""
    for candidate in (rel, *(rel + suffix for suffix in IMAGE_SUFFIXES)):
        path = _inside(root, candidate, source, field)
        if path.is_file():
            return path
    raise FormatError(source, field, f"image {rel!r} not found in {root.root}")


def _nerfstudio_camera(doc: NerfTransforms, image: Path, limits: ImageLimits) -> PinholeCamera:
    """The shared camera: fl_x.. as given (fl_y, cx, cy defaulting as nerfstudio's loader does), or NeRF-synthetic's
    horizontal field of view with the principal point at the centre of the first image."""
    fields = {f.camera for f in doc.frames}
    if len(fields) != 1:
        raise FormatError(doc.source, "frames", "frames have different intrinsics; one shared camera is supported")
    cam = fields.pop()
    width, height = checked_size(image, "frames[0].file_path", limits)
    if cam.fx is None and cam.angle_x is not None:
        fx = 0.5 * width / math.tan(0.5 * cam.angle_x)
        cam = CameraFields(width, height, fx, fx, width / 2.0, height / 2.0)
    w, h = cam.width or width, cam.height or height
    fy = cam.fy if cam.fy is not None else cam.fx
    cx, cy = (cam.cx if cam.cx is not None else w / 2.0), (cam.cy if cam.cy is not None else h / 2.0)
    return pinhole(CameraFields(w, h, cam.fx, fy, cx, cy), doc.source)


def read_nerfstudio(src: Path, limits: ImageLimits = DEFAULT_LIMITS) -> SourceDataset:
    """transforms.json (nerfstudio) or transforms_train.json (NeRF-synthetic) in `src`."""
    root = ScanFolder(src)
    path = next((src / n for n in ("transforms.json", "transforms_train.json") if (src / n).is_file()), None)
    if path is None:
        raise BadInputError(f"{src}: no transforms.json or transforms_train.json")
    lens_fields, data = split_nerfstudio_lens(read_json_object(_inside(root, path.name, path, None)), path)
    doc = parse_transforms(data, path)
    frames = []
    for i, raw in enumerate(doc.frames):
        image = _find_image(root, raw.file_path, path, f"frames[{i}].file_path")
        mask = None
        if raw.mask_path is not None:
            mask = _inside(root, raw.mask_path, path, f"frames[{i}].mask_path")
            if not mask.is_file():
                raise FormatError(path, f"frames[{i}].mask_path", f"{mask} not found")
        frames.append(SourceFrame(image, mask, opengl_to_opencv(raw.c2w_gl)))
    intr = _nerfstudio_camera(doc, frames[0].image, limits)
    return SourceDataset(intr, frames, lens=lens_from_nerfstudio(lens_fields, intr, str(path)))


def _colmap_dirs(root: ScanFolder) -> tuple[Path, Path]:
    """The model folder and images/ beside it, both inside the source: no parent folder is searched."""
    src = root.root
    for rel in (".", "sparse/0", "sparse", "colmap"):
        model = _inside(root, rel, src, rel)
        if any((model / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            for images_rel in dict.fromkeys(("images", str(Path(rel).parent / "images"), str(Path(rel).parent.parent / "images"))):
                images = _inside(root, images_rel, src, images_rel)
                if images.is_dir():
                    return model, images
            raise BadInputError(f"{src}: COLMAP model found in {model} but no images/ folder beside it inside {src}")
    raise BadInputError(f"{src}: no COLMAP model (cameras.bin/.txt) in ., sparse/0, sparse or colmap")


def read_colmap(src: Path, limits: ImageLimits = DEFAULT_LIMITS) -> SourceDataset:
    root = ScanFolder(src)
    model_dir, image_dir = _colmap_dirs(root)
    for file in model_dir.iterdir():
        if file.stem in ("cameras", "images", "points3D", "rigs", "frames"):
            _inside(root, file, model_dir, file.name)
    check_colmap_binary(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap's C++ reader raises many types on a malformed model
        raise FormatError(model_dir, None, f"unreadable COLMAP model ({type(exc).__name__}: {exc})") from exc
    if rec.num_cameras() != 1:
        raise BadInputError(f"{model_dir}: {rec.num_cameras()} cameras; one shared camera is supported")
    camera = next(iter(rec.cameras.values()))
    k = camera.calibration_matrix()
    cam = PinholeCamera(int(camera.width), int(camera.height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    check_camera(cam, f"{model_dir}: camera {camera.camera_id}")
    lens = lens_from_colmap(camera, str(model_dir))
    intr = lens.intrinsics
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        path = _inside(root, image_dir / image.name, model_dir, f"image {image.name!r}")
        if not path.is_file():
            raise BadInputError(f"{model_dir}: image {image.name!r} not found in {image_dir}")
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        frames.append(SourceFrame(path, None, _rigid_inverse(w2c, model_dir, f"image {image.name!r}")))
    if not frames:
        raise BadInputError(f"{model_dir}: no registered images")
    points = None
    if rec.num_points3D():
        pts = list(rec.points3D.values())
        points = (np.array([p.xyz for p in pts]), np.array([p.color for p in pts], dtype=np.uint8))
    return SourceDataset(intr, frames, points, lens)


def _rigid_inverse(w2c: np.ndarray, source: object, field: str) -> np.ndarray:
    """camera-to-world of a world-to-camera that must be finite and rigid (a singular one is refused, not inverted)."""
    if not np.isfinite(w2c).all():
        raise FormatError(source, field, "pose holds NaN or infinity")
    check_rotation(w2c, source, field)
    c2w = np.eye(4)
    c2w[:3, :3] = w2c[:3, :3].T
    c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
    return c2w


def _decompose_projection(p: np.ndarray, source: object, field: str) -> tuple[np.ndarray, np.ndarray]:
    """P = K [R | t] -> (K with K[2,2] = 1, camera-to-world); a singular or non-finite P is refused."""
    p = np.asarray(p, dtype=np.float64)[:3, :4]
    if not np.isfinite(p).all():
        raise FormatError(source, field, "projection matrix holds NaN or infinity")
    if not np.linalg.cond(p[:, :3]) < 1e12:  # inf or NaN for an all-zero block
        raise FormatError(source, field, "projection matrix is singular (its left 3x3 has no inverse)")
    # OpenCV splits P into K, R (world-to-camera) and the homogeneous centre.
    k, r, centre = cv2.decomposeProjectionMatrix(p)[:3]
    if not np.isfinite(k).all() or abs(k[2, 2]) < 1e-12 or abs(centre[3, 0]) < 1e-12:
        raise FormatError(source, field, "projection matrix does not decompose into K [R | t]")
    k = k / k[2, 2]
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = centre[:3, 0] / centre[3, 0]
    check_rotation(c2w, source, field)
    return k, c2w


def read_idr(src: Path, limits: ImageLimits = DEFAULT_LIMITS) -> SourceDataset:
    """IDR/NeuS layout: cameras.npz (or cameras_sphere.npz), image/, optional mask/; all inside `src`."""
    root = ScanFolder(src)
    npz = next((src / n for n in ("cameras.npz", "cameras_sphere.npz") if (src / n).is_file()), None)
    if npz is None:
        raise BadInputError(f"{src}: no cameras.npz or cameras_sphere.npz")
    npz = _inside(root, npz.name, src, npz.name)
    images = _listed_images(root, "image")
    if not images:
        raise BadInputError(f"{src / 'image'}: no images")
    masks = _listed_images(root, "mask")
    if masks and len(masks) != len(images):
        raise BadInputError(f"{src / 'mask'}: {len(masks)} masks for {len(images)} images")
    try:
        cams = dict(np.load(npz, allow_pickle=False))
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(npz, None, f"unreadable ({exc})") from exc
    frames, ks = [], []
    for i, image in enumerate(images):
        key = f"world_mat_{i}"
        if key not in cams or np.shape(cams[key]) not in ((4, 4), (3, 4)) or cams[key].dtype.kind not in "iuf":
            raise FormatError(npz, key, f"missing, or not a numeric 4x4 / 3x4 matrix, for {image.name}")
        k, c2w = _decompose_projection(cams[key], npz, key)
        frames.append(SourceFrame(image, masks[i] if masks else None, c2w))
        ks.append(k)
    k = np.mean(ks, axis=0)
    if np.abs(np.array(ks) - k).max() > 1e-3 * abs(k[0, 0]):
        raise FormatError(npz, "world_mat_*", "intrinsics differ between views; one shared camera is supported")
    width, height = checked_size(images[0], "image", limits)
    cam = PinholeCamera(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    check_camera(cam, npz)
    return SourceDataset(cam, frames)


def read_middlebury(src: Path, limits: ImageLimits = DEFAULT_LIMITS) -> SourceDataset:
    """Middlebury multi-view: the one `*_par.txt` in `src`, and the images it names, all inside `src`."""
    root = ScanFolder(src)
    pars = sorted(p for p in src.iterdir() if p.name.endswith("_par.txt"))
    if len(pars) != 1:
        found = ", ".join(p.name for p in pars) or "none"
        raise BadInputError(f"{src}: expected exactly one <set>_par.txt camera file, found {found}")
    par = _inside(root, pars[0].name, src, pars[0].name)
    if not par.is_file():
        raise BadInputError(f"{par}: not a file")
    cameras = parse_par(par.read_bytes(), par)
    k = shared_k(cameras, par)
    frames = []
    for cam in cameras:
        image = _inside(root, cam.name, par, f"line {cam.line}")
        if image.suffix.lower() not in IMAGE_SUFFIXES or not image.is_file():
            raise FormatError(par, f"line {cam.line}", f"image {cam.name!r} not found in {src} (or not a .png/.jpg)")
        frames.append(SourceFrame(image, None, _rigid_inverse(cam.w2c, par, f"line {cam.line}")))
    width, height = checked_size(frames[0].image, f"line {cameras[0].line}", limits)
    cam = PinholeCamera(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    check_camera(cam, par)
    return SourceDataset(cam, frames)


READERS = {"nerfstudio": read_nerfstudio, "colmap": read_colmap, "idr": read_idr, "middlebury": read_middlebury}


def import_dataset(src: Path, fmt: Format, out: Path, settings: ImportSettings | None = None) -> ImportReport:
    """Read `src` in format `fmt`, convert to metres and station axes, and write scan folder `out`."""
    started = time.monotonic()
    settings = settings or ImportSettings()
    if fmt not in READERS:
        raise BadInputError(f"import: unknown format {fmt!r} (choose from {', '.join(READERS)})")
    if settings.masks not in get_args(MaskSource):
        raise BadInputError(f"import: masks {settings.masks!r}: expected one of {', '.join(get_args(MaskSource))}")
    src = Path(src).resolve()
    if not src.is_dir():
        raise BadInputError(f"import: source {src} is not a folder")
    data = READERS[fmt](src, settings.image_limits)
    check_camera(data.intrinsics, src)
    units = settings.units_to_m if settings.units_to_m is not None else DEFAULT_UNITS_TO_M[fmt]
    if not units > 0:
        raise BadInputError(f"import: units_to_m must be positive, got {units}")
    orient = DEFAULT_ORIENT[fmt] if settings.orient == "auto" else settings.orient
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
        with open_pil(frame.image, f"frames[{i}] image", settings.image_limits) as img:
            if img.size != (data.intrinsics.width, data.intrinsics.height):
                raise FormatError(frame.image, None, f"size {img.size} differs from the camera's "
                                                     f"{data.intrinsics.width}x{data.intrinsics.height}")
            rgba = img.convert("RGBA") if img.mode in ("RGBA", "LA", "PA") else None
            rgb = np.asarray(img.convert("RGB"))  # [H, W, 3]
        # kept as given: 255 is object, a value between is its coverage (an alpha channel is straight alpha,
        # so the RGB already holds the object's own colour there, the form our masks and images take too)
        coverage = None
        if frame.mask is not None:
            with open_pil(frame.mask, f"frames[{i}] mask", settings.image_limits) as m:
                if m.size != img.size:
                    raise FormatError(frame.mask, None, f"mask size {m.size} differs from its image's {img.size}")
                coverage = np.asarray(m.convert("L"))
            mask_kind = "files"
        elif rgba is not None:
            coverage = np.asarray(rgba)[:, :, 3]
            mask_kind = "alpha"
        elif settings.masks == "dark-backdrop":
            coverage = dark_backdrop_mask(rgb)
            if not coverage.any():
                raise FormatError(frame.image, None, "--masks dark-backdrop found no object brighter than the backdrop")
            mask_kind = "dark-backdrop"
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

