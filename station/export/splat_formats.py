"""The splat formats station writes and reads, in one table keyed by file suffix.

Each codec module turns a turntable-frame SplatModel into bytes in its format's own frame and back
(docs/formats.md); this table is the one place that reads and writes files, so every format gets the
same typed error on an unreadable file and the same atomic write.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from station.errors import BadInputError
from station.export import dotsplat, gltf, ply, spz
from station.export.splat_model import SplatModel
from station.scanfolder import atomic_write_bytes


@dataclass(frozen=True)
class SplatFormat:
    name: str
    encode: Callable[[SplatModel], bytes]
    decode: Callable[[bytes, Path], SplatModel]


FORMATS = {
    ".ply": SplatFormat("INRIA 3DGS PLY", ply.encode_ply, ply.decode_ply),
    ".splat": SplatFormat("antimatter15 .splat", dotsplat.encode_splat, dotsplat.decode_splat),
    ".spz": SplatFormat("Niantic SPZ v3", spz.encode_spz, spz.decode_spz),
    ".glb": SplatFormat("glTF 2.0 binary, KHR_gaussian_splatting", gltf.encode_glb, gltf.decode_glb),
}


def format_of(path: Path) -> SplatFormat:
    try:
        return FORMATS[Path(path).suffix.lower()]
    except KeyError:
        raise BadInputError(f"{path}: unknown splat format (one of {', '.join(FORMATS)})") from None


def read_splat(path: Path) -> SplatModel:
    """Turntable-frame model of a splat file; BadInputError naming the file on anything malformed."""
    path = Path(path)
    fmt = format_of(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BadInputError(f"{path}: cannot read {fmt.name} ({exc.strerror})") from exc
    return fmt.decode(data, path)


def write_splat(path: Path, model: SplatModel) -> None:
    """Write a turntable-frame model in the format its suffix names, atomically."""
    atomic_write_bytes(Path(path), format_of(path).encode(model))
