"""poses/transforms.json: the nerfstudio-convention pose file, written and read with validation.

nerfstudio stores camera-to-world in OpenGL axes (x right, y up, z back); COLMAP and OpenCV use
y down, z forward. Inside the station every pose is OpenCV; the flip happens here and only here.
The file comes from an untrusted scan folder: its fields are checked by `station.formats.transforms`
(the one parser process, ngs and import share) and every path it names must resolve inside the folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from station.errors import FormatError, ScanFolderError
from station.formats.jsonfile import read_json_object
from station.formats.transforms import PinholeCamera, check_camera, check_rotation, parse_transforms, shared_pinhole
from station.rig_geometry import opencv_to_opengl
from station.scanfolder import ScanFolder, atomic_write_json

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
    intrinsics: PinholeCamera
    frames: list[PosedFrame]
    ply_file_path: str | None = None


def write_transforms(scan: ScanFolder, transforms: Transforms) -> Path:
    """Write poses/transforms.json. Paths are relative to the scan folder (images/..., masks/...), as the contract says.
    The camera and poses pass the reader's checks first: no stage may write what training would refuse."""
    intr = transforms.intrinsics
    source = scan.transforms_path
    check_camera(PinholeCamera(int(intr.width), int(intr.height), intr.fx, intr.fy, intr.cx, intr.cy), source)
    for i, frame in enumerate(transforms.frames):
        c2w = np.asarray(frame.c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise FormatError(source, f"frames[{i}].transform_matrix", "not a finite 4x4 matrix")
        check_rotation(c2w, source, f"frames[{i}].transform_matrix")
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


def _relative_path(scan: ScanFolder, value: str, source: Path, field: str, must_exist: bool) -> str:
    """transforms.json paths are relative to the scan folder (nerfstudio: to the file's data root)."""
    try:
        resolved = scan.resolve_inside(value)
    except ScanFolderError as exc:
        raise FormatError(source, field, f"{value!r} resolves outside the scan folder") from exc
    if must_exist and not resolved.is_file():
        raise FormatError(source, field, f"{value!r} does not exist in {scan.root}")
    return value


def read_transforms(scan: ScanFolder, check_files: bool = True) -> Transforms:
    """Read and validate poses/transforms.json (station.formats.transforms); poses come back in OpenCV axes."""
    source = scan.resolve_inside("poses/transforms.json")  # a link out of the folder is refused, not followed
    doc = parse_transforms(read_json_object(source), source)
    cam = shared_pinhole(doc)
    frames = []
    for i, frame in enumerate(doc.frames):
        file_path = _relative_path(scan, frame.file_path, source, f"frames[{i}].file_path", check_files)
        mask_path = None
        if frame.mask_path is not None:
            mask_path = _relative_path(scan, frame.mask_path, source, f"frames[{i}].mask_path", check_files)
        frames.append(PosedFrame(file_path, opengl_to_opencv(frame.c2w_gl), mask_path))
    ply = doc.ply_file_path
    if ply is not None:
        ply = _relative_path(scan, ply, source, "ply_file_path", check_files)
    return Transforms(cam, frames, ply)
