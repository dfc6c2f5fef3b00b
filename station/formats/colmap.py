"""COLMAP binary models (cameras.bin, images.bin, points3D.bin): every count checked against the bytes.

COLMAP's reader reserves memory for the counts a file states: a garbage points3D.bin made it take
over 10 GB, and a truncated cameras.bin was read without complaint. The layout is walked here, with
offsets only, before pycolmap sees the files (format: colmap/src/colmap/scene/reconstruction_io.cc).
"""

from __future__ import annotations

import struct
from pathlib import Path

from station.errors import FormatError

# model id -> number of parameters (colmap/src/colmap/sensor/models.h)
CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}
MIN_RECORD = {"rigs.bin": 8, "frames.bin": 72}  # checked by count only: the smallest record a count may promise


class _Reader:
    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str, field: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise FormatError(self.path, field, f"truncated at byte {self.at} of {len(self.data)}")
        values = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, field: str, record_bytes: int) -> int:
        (n,) = self.take("<Q", field)
        if n * record_bytes > len(self.data) - self.at:
            raise FormatError(self.path, field, f"states {n} records, more than its {len(self.data)} bytes can hold")
        return n

    def name(self, field: str) -> None:
        end = self.data.find(b"\x00", self.at)
        if end < 0:
            raise FormatError(self.path, field, "unterminated image name")
        self.at = end + 1

    def finish(self) -> None:
        if self.at != len(self.data):
            raise FormatError(self.path, None, f"{len(self.data) - self.at} bytes after the last record")


def _cameras(reader: _Reader) -> None:
    for i in range(reader.count("num_cameras", 24)):
        _, model, _, _ = reader.take("<iiQQ", f"camera {i}")
        if model not in CAMERA_PARAMS:
            raise FormatError(reader.path, f"camera {i}", f"unknown camera model id {model}")
        reader.take(f"<{CAMERA_PARAMS[model]}d", f"camera {i} params")


def _images(reader: _Reader) -> None:
    for i in range(reader.count("num_images", 73)):
        reader.take("<I7dI", f"image {i}")
        reader.name(f"image {i} name")
        points = reader.count(f"image {i} num_points2D", 24)
        reader.take(f"<{24 * points}x", f"image {i} points2D")


def _points(reader: _Reader) -> None:
    for i in range(reader.count("num_points3D", 51)):
        reader.take("<Q3d3Bd", f"point {i}")
        track = reader.count(f"point {i} track_length", 8)
        reader.take(f"<{8 * track}x", f"point {i} track")


def check_colmap_binary(model_dir: Path) -> None:
    """Refuse a binary model whose counts overrun its bytes or that is truncated (text models pass through)."""
    walkers = {"cameras.bin": _cameras, "images.bin": _images, "points3D.bin": _points}
    for name, walk in walkers.items():
        if (model_dir / name).is_file():
            reader = _Reader(model_dir / name)
            walk(reader)
            reader.finish()
    for name, record in MIN_RECORD.items():
        if (model_dir / name).is_file():
            _Reader(model_dir / name).count(f"num_{name.split('.')[0]}", record)
