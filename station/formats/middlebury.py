"""Middlebury multi-view `<set>_par.txt` (Seitz et al.): one camera per line, checked line by line.

Each line is "imgname.png k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 .. r33 t1 t2 t3": the projection is
K [R | t], world to image, OpenCV axes (x right, y down, looking along +z). The published files start
with a line holding the camera count; it is accepted and must match. Every problem names the file and
the line, so an operator can fix it; names are returned as given and resolved by the caller.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from station.errors import FormatError, InputTooLargeError
from station.formats.transforms import MAX_FRAMES, check_rotation

MAX_PAR_BYTES = 4 * 1024 * 1024  # ~250 bytes a line: 10,000 cameras fit with room to spare
FIELDS = 1 + 9 + 9 + 3
K_ZERO_TOL = 1e-9  # relative to the focal length: what a printed 0.000000 is


@dataclass
class ParCamera:
    name: str
    k: np.ndarray  # [3, 3] upper triangular, k33 = 1, zero skew
    w2c: np.ndarray  # [4, 4] world-to-camera, rigid
    line: int  # 1-based, for messages


def _numbers(fields: list[str], path: Path, where: str) -> np.ndarray:
    try:
        values = np.array([float(f) for f in fields])
    except ValueError as exc:
        raise FormatError(path, where, f"not a number ({exc})") from exc
    if not np.isfinite(values).all():
        raise FormatError(path, where, "holds NaN or infinity")
    return values


def _check_k(k: np.ndarray, path: Path, where: str) -> np.ndarray:
    """Upper triangular with positive focals and no skew (the rasteriser's pinhole has none), scaled to k33 = 1."""
    if not k[2, 2] > 0:
        raise FormatError(path, where, f"K: k33 must be positive, got {k[2, 2]:g}")
    k = k / k[2, 2]
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise FormatError(path, where, f"K: focal lengths k11, k22 must be positive, got {k[0, 0]:g}, {k[1, 1]:g}")
    tol = K_ZERO_TOL * max(k[0, 0], k[1, 1])
    if max(abs(k[1, 0]), abs(k[2, 0]), abs(k[2, 1])) > tol:
        raise FormatError(path, where, "K is not upper triangular (k21, k31, k32 must be 0)")
    if abs(k[0, 1]) > tol:
        raise FormatError(path, where, f"K has skew k12 = {k[0, 1]:g}; only zero skew is supported")
    return k


def parse_par(data: bytes, path: Path) -> list[ParCamera]:
    """The cameras of a `_par.txt` file's bytes, in file order; names unique."""
    if len(data) > MAX_PAR_BYTES:
        raise InputTooLargeError(path, None, f"{len(data)} bytes, over the {MAX_PAR_BYTES} limit")
    try:
        text = data.decode("utf-8-sig")  # a byte-order mark from a Windows editor is not a field
    except UnicodeDecodeError as exc:
        raise FormatError(path, None, f"not UTF-8 text (byte {exc.start})") from exc
    lines = [(n, line.split()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    count = None
    if lines and len(lines[0][1]) == 1:
        n, (first,) = lines.pop(0)
        if not first.isdigit():
            raise FormatError(path, f"line {n}", f"expected the camera count or a camera line, got {first!r}")
        count = int(first)
    if not lines:
        raise FormatError(path, None, "no camera lines")
    if len(lines) > MAX_FRAMES:
        raise InputTooLargeError(path, None, f"{len(lines)} cameras, over the {MAX_FRAMES} limit")
    if count is not None and count != len(lines):
        raise FormatError(path, "line 1", f"says {count} cameras but {len(lines)} camera lines follow")
    cameras: list[ParCamera] = []
    seen: dict[str, int] = {}
    for n, fields in lines:
        where = f"line {n}"
        if len(fields) != FIELDS:
            raise FormatError(path, where, f"{len(fields)} fields; expected {FIELDS} "
                                           "(imgname k11..k33 r11..r33 t1 t2 t3)")
        name = fields[0]
        if name in seen:
            raise FormatError(path, where, f"image {name!r} already given on line {seen[name]}")
        seen[name] = n
        values = _numbers(fields[1:], path, where)
        k = _check_k(values[:9].reshape(3, 3), path, where)
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = values[9:18].reshape(3, 3), values[18:]
        check_rotation(w2c, path, f"{where}: R")
        cameras.append(ParCamera(name, k, w2c, n))
    return cameras


def shared_k(cameras: list[ParCamera], path: Path) -> np.ndarray:
    """The one K every line gives (to a part in a thousand of the focal): one shared camera is supported."""
    k = cameras[0].k
    for cam in cameras[1:]:
        if np.abs(cam.k - k).max() > 1e-3 * k[0, 0]:
            raise FormatError(path, f"line {cam.line}", f"K differs from line {cameras[0].line}'s; "
                                                         "one shared camera is supported")
    return k
