"""transforms.json (nerfstudio / NeRF-synthetic): the one parser behind process, ngs and import.

It checks what a pinhole camera and a rigid pose must be, so nothing downstream trains on garbage:
focal lengths giving a field of view between MIN_FOV_DEG and MAX_FOV_DEG (0, negative, 1e-30 and
`true` are refused), a principal point near the image, no lens distortion (the rasteriser has
none), and camera-to-world matrices whose upper 3x3 is a rotation (no mirror, no scale). Paths are
returned as given; the caller resolves them inside its folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from station.errors import FormatError, InputTooLargeError
from station.formats.jsonfile import finite_number, is_number, text, whole_number

MAX_FRAMES = 10_000
MAX_IMAGE_SIDE = 65_536
MIN_FOV_DEG, MAX_FOV_DEG = 0.05, 179.0
ROTATION_TOL = 1e-4
MAX_TRANSLATION = 1e6  # source units; anything larger is a corrupt file, not a scene
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels, shared by every stage; a lens's distortion is in `process.lens.Lens`
    and undistorted before training."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


@dataclass(frozen=True)
class CameraFields:
    """The intrinsics a file gives, each None where absent (NeRF-synthetic gives only `camera_angle_x`)."""

    width: int | None = None
    height: int | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    angle_x: float | None = None


@dataclass(frozen=True)
class NerfFrame:
    file_path: str
    mask_path: str | None
    c2w_gl: np.ndarray  # [4, 4] camera-to-world, OpenGL axes, source units
    camera: CameraFields  # the file's camera with this frame's overrides


@dataclass(frozen=True)
class NerfTransforms:
    source: str
    camera: CameraFields
    frames: list[NerfFrame]
    ply_file_path: str | None


def _fov_deg(side: float, focal: float) -> float:
    return math.degrees(2.0 * math.atan(0.5 * side / focal))


def pinhole(fields: CameraFields, source: object) -> PinholeCamera:
    """A complete, plausible pinhole camera from `fields`; names the first missing or implausible field."""
    values = {"w": fields.width, "h": fields.height, "fl_x": fields.fx, "fl_y": fields.fy, "cx": fields.cx, "cy": fields.cy}
    for key, value in values.items():
        if value is None:
            raise FormatError(source, key, "missing")
    cam = PinholeCamera(fields.width, fields.height, fields.fx, fields.fy, fields.cx, fields.cy)  # type: ignore[arg-type]
    check_camera(cam, source)
    return cam


def check_camera(cam: PinholeCamera, source: object) -> None:
    """Refuse intrinsics no lens has: also used before anything writes a transforms.json."""
    for key, side in (("w", cam.width), ("h", cam.height)):
        if not (isinstance(side, int) and 1 <= side <= MAX_IMAGE_SIDE):
            raise FormatError(source, key, f"image side must be 1..{MAX_IMAGE_SIDE} pixels, got {side!r}")
    for key, focal, side in (("fl_x", cam.fx, cam.width), ("fl_y", cam.fy, cam.height)):
        finite_number(focal, source, key, positive=True)
        fov = _fov_deg(side, focal)
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise FormatError(source, key, f"focal {focal:g} px gives a {fov:.3g} deg field of view over {side} px "
                                           f"(plausible: {MIN_FOV_DEG}..{MAX_FOV_DEG})")
    for key, centre, side in (("cx", cam.cx, cam.width), ("cy", cam.cy, cam.height)):
        finite_number(centre, source, key, low=-float(side), high=2.0 * side)


def check_rotation(mat: np.ndarray, source: object, field: str) -> None:
    """The upper 3x3 of a camera-to-world must be a proper rotation: mirrored or scaled poses are refused."""
    rot = mat[:3, :3]
    if not np.allclose(rot.T @ rot, np.eye(3), atol=ROTATION_TOL):
        raise FormatError(source, field, "upper 3x3 is not a rotation (scaled, sheared or singular)")
    if np.linalg.det(rot) < 0:
        raise FormatError(source, field, "upper 3x3 is not a rotation (mirrored: determinant -1)")
    if np.abs(mat[:3, 3]).max() > MAX_TRANSLATION:
        raise FormatError(source, field, f"translation beyond {MAX_TRANSLATION:g} units")


def pose_matrix(value: Any, source: object, field: str) -> np.ndarray:
    """A 4x4 (or 3x4, completed) finite rigid camera-to-world from nested JSON lists of numbers."""
    rows = value if isinstance(value, list) else None
    if rows is None or len(rows) not in (3, 4) or not all(
            isinstance(row, list) and len(row) == 4 and all(is_number(v) for v in row) for row in rows):
        raise FormatError(source, field, "must be a 4x4 (or 3x4) list of numbers")
    mat = np.eye(4)
    mat[: len(rows)] = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(mat).all():
        raise FormatError(source, field, "holds NaN or infinity")
    if not np.allclose(mat[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise FormatError(source, field, f"last row must be 0 0 0 1, got {mat[3].tolist()}")
    check_rotation(mat, source, field)
    return mat


def camera_fields(raw: dict, source: object, prefix: str, base: CameraFields | None = None) -> CameraFields:
    """The intrinsics keys present in `raw`, checked by type and range; absent ones come from `base`."""
    base = base or CameraFields()

    def get(key: str, current: Any, check) -> Any:
        return current if key not in raw else check(raw[key], source, f"{prefix}{key}")

    def side(value: Any, src: object, field: str) -> int:
        return whole_number(value, src, field, 1, MAX_IMAGE_SIDE)

    def positive(value: Any, src: object, field: str) -> float:
        return finite_number(value, src, field, positive=True)

    def centre(value: Any, src: object, field: str) -> float:
        return finite_number(value, src, field)

    def angle(value: Any, src: object, field: str) -> float:
        return finite_number(value, src, field, low=math.radians(MIN_FOV_DEG), high=math.radians(MAX_FOV_DEG))

    for key in DISTORTION_KEYS:
        if key in raw and finite_number(raw[key], source, f"{prefix}{key}") != 0.0:
            raise FormatError(source, f"{prefix}{key}", "distorted cameras are not supported: undistort first")
    if "camera_model" in raw and raw["camera_model"] not in CAMERA_MODELS:
        raise FormatError(source, f"{prefix}camera_model", f"must be one of {', '.join(CAMERA_MODELS)}, "
                                                          f"got {str(raw['camera_model'])[:40]!r}")
    return CameraFields(
        get("w", base.width, side), get("h", base.height, side), get("fl_x", base.fx, positive),
        get("fl_y", base.fy, positive), get("cx", base.cx, centre), get("cy", base.cy, centre),
        get("camera_angle_x", base.angle_x, angle),
    )


def _optional_path(raw: dict, key: str, source: object, field: str) -> str | None:
    return None if raw.get(key) is None else text(raw[key], source, field)


def parse_transforms(data: Any, source: object) -> NerfTransforms:
    """Check a decoded transforms.json; intrinsics may be per file or per frame (nerfstudio allows both)."""
    if not isinstance(data, dict):
        raise FormatError(source, None, "expected a JSON object at the top level")
    camera = camera_fields(data, source, "")
    frames_raw = data.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise FormatError(source, "frames", "must be a non-empty list")
    if len(frames_raw) > MAX_FRAMES:
        raise InputTooLargeError(source, "frames", f"{len(frames_raw)} frames exceeds the limit of {MAX_FRAMES}")
    frames = []
    for i, raw in enumerate(frames_raw):
        where = f"frames[{i}]"
        if not isinstance(raw, dict):
            raise FormatError(source, where, "must be an object")
        frames.append(NerfFrame(
            text(raw.get("file_path"), source, f"{where}.file_path"),
            _optional_path(raw, "mask_path", source, f"{where}.mask_path"),
            pose_matrix(raw.get("transform_matrix"), source, f"{where}.transform_matrix"),
            camera_fields(raw, source, f"{where}.", camera),
        ))
    return NerfTransforms(str(source), camera, frames, _optional_path(data, "ply_file_path", source, "ply_file_path"))


def shared_pinhole(doc: NerfTransforms) -> PinholeCamera:
    """The one complete camera every frame shares; per-frame intrinsics that differ are refused."""
    cams = {pinhole(f.camera, doc.source) for f in doc.frames}
    if len(cams) != 1:
        raise FormatError(doc.source, "frames", "frames have different intrinsics; one shared camera is supported")
    return cams.pop()
