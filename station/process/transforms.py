"""poses/transforms.json: the nerfstudio-convention pose file, written and read with validation.

nerfstudio stores camera-to-world in OpenGL axes (x right, y up, z back); COLMAP and OpenCV use
y down, z forward. Inside the station every pose is OpenCV; the flip happens here and only here.
The file comes from an untrusted scan folder, so every path it names must resolve inside the
folder, the counts must be sane, and every field is checked before use.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.process.sfm import Intrinsics
from station.rig_geometry import opencv_to_opengl
from station.scanfolder import ScanFolder, atomic_write_json

MAX_FRAMES = 100_000
MAX_IMAGE_SIDE = 65_536


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Inverse of `opencv_to_opengl` (the flip of the y and z camera axes is its own inverse)."""
    return opencv_to_opengl(c2w)


@dataclass(frozen=True)
class PosedFrame:
    file_path: str  # relative to the scan folder, e.g. images/e0_a000.png
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world, metres, turntable frame
    mask_path: str | None = None


@dataclass(frozen=True)
class Transforms:
    intrinsics: Intrinsics
    frames: list[PosedFrame]
    ply_file_path: str | None = None


def write_transforms(scan: ScanFolder, transforms: Transforms) -> Path:
    """Write poses/transforms.json. Paths are relative to the scan folder (images/..., masks/...), as the contract says."""
    intr = transforms.intrinsics
    data: dict = {
        "camera_model": "OPENCV",
        "fl_x": intr.fx,
        "fl_y": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "w": intr.width,
        "h": intr.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": [],
    }
    for frame in transforms.frames:
        scan.resolve_inside(frame.file_path)
        entry = {"file_path": frame.file_path, "transform_matrix": opencv_to_opengl(frame.c2w).tolist()}
        if frame.mask_path is not None:
            scan.resolve_inside(frame.mask_path)
            entry["mask_path"] = frame.mask_path
        data["frames"].append(entry)
    if transforms.ply_file_path is not None:
        scan.resolve_inside(transforms.ply_file_path)
        data["ply_file_path"] = transforms.ply_file_path
    atomic_write_json(scan.transforms_path, data)
    return scan.transforms_path


def _number(data: dict, key: str, where: str, positive: bool = True) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise BadInputError(f"{where}: field {key!r} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise BadInputError(f"{where}: field {key!r} must be positive, got {value!r}")
    return float(value)


def _relative_path(scan: ScanFolder, value: object, where: str, must_exist: bool) -> str:
    """transforms.json paths are relative to the scan folder (nerfstudio: to the file's data root)."""
    if not isinstance(value, str) or not value:
        raise BadInputError(f"{where}: expected a relative path string, got {value!r}")
    resolved = scan.resolve_inside(value)
    if must_exist and not resolved.is_file():
        raise BadInputError(f"{where}: {value!r} does not exist in {scan.root}")
    return value


def read_transforms(scan: ScanFolder, check_files: bool = True) -> Transforms:
    """Read and validate poses/transforms.json; poses come back in OpenCV axes."""
    path = scan.transforms_path
    data = scan.read_json(path)
    where = str(path)
    width, height = int(_number(data, "w", where)), int(_number(data, "h", where))
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise BadInputError(f"{where}: image size {width}x{height} is implausible")
    intr = Intrinsics(
        width, height, _number(data, "fl_x", where), _number(data, "fl_y", where),
        _number(data, "cx", where), _number(data, "cy", where),
    )
    frames_raw = data.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise BadInputError(f"{where}: field 'frames' must be a non-empty list")
    if len(frames_raw) > MAX_FRAMES:
        raise BadInputError(f"{where}: {len(frames_raw)} frames exceeds the limit of {MAX_FRAMES}")
    frames = []
    for i, raw in enumerate(frames_raw):
        fwhere = f"{where}: frames[{i}]"
        if not isinstance(raw, dict):
            raise BadInputError(f"{fwhere}: must be an object")
        file_path = _relative_path(scan, raw.get("file_path"), f"{fwhere}.file_path", check_files)
        mask_path = None
        if raw.get("mask_path") is not None:
            mask_path = _relative_path(scan, raw["mask_path"], f"{fwhere}.mask_path", check_files)
        try:
            mat = np.asarray(raw.get("transform_matrix"), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise BadInputError(f"{fwhere}.transform_matrix: not a numeric matrix ({exc})") from exc
        if mat.shape != (4, 4) or not np.isfinite(mat).all():
            raise BadInputError(f"{fwhere}.transform_matrix: must be a finite 4x4 matrix, got shape {mat.shape}")
        rot = mat[:3, :3]
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4) or np.linalg.det(rot) < 0:
            raise BadInputError(f"{fwhere}.transform_matrix: upper 3x3 is not a rotation")
        frames.append(PosedFrame(file_path, opengl_to_opencv(mat), mask_path))
    ply = data.get("ply_file_path")
    if ply is not None:
        ply = _relative_path(scan, ply, f"{where}: ply_file_path", check_files)
    return Transforms(intr, frames, ply)
