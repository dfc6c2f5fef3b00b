"""The one reader of binary splat PLYs: header checked whole, body sized exactly, then `station sos
--splat` turns the vertex table into Gaussians (and station.export.ply into its SplatModel).

Layout (binary little-endian, per vertex): x y z, [nx ny nz], f_dc_0..2, f_rest_0..(3K-4),
opacity (logit), scale_0..2 (log), rot_0..3 (wxyz). f_rest is channel-major: all R coefficients,
then all G, then all B. The file is untrusted: elements may come in any order (a `face` before
`vertex` is skipped, not read as splats), a property may not repeat, and the body must hold exactly
the bytes the header promises, no fewer and no more.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from station.errors import BadInputError
from station.ngs.gaussians import Gaussians

PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
             "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
             "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
MAX_HEADER = 64 * 1024
# station's asset writer marks its y-down splats (station.export.ply) with this comment; --splat takes
# a PLY in the scan's own frame, so it refuses one rather than score it lying on its side.
VIEWER_FRAME_COMMENT = "station splat: metres, origin turntable centre on the plate, y down (3DGS convention)"
MAX_LIST_ROWS = 5_000_000  # a list element (faces) is walked row by row; more than this is not a splat file


@dataclass
class _Element:
    name: str
    count: int
    scalars: list[tuple[str, str]] = field(default_factory=list)
    lists: dict[str, tuple[str, str]] = field(default_factory=dict)  # name -> (count type, item type)
    order: list[str] = field(default_factory=list)


def _header(data: bytes, source: Path) -> tuple[list[_Element], int, list[str]]:
    """Elements in file order, the body's offset and the comments; BadInputError on anything malformed."""
    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise BadInputError(f"{source}: not a PLY file (no 'ply' magic line)")
    end = data.find(b"end_header", 0, MAX_HEADER)
    newline = data.find(b"\n", end) if end >= 0 else -1
    if end < 0 or newline < 0:
        raise BadInputError(f"{source}: not a PLY file (no end_header line within {MAX_HEADER} bytes)")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as exc:
        raise BadInputError(f"{source}: PLY header is not ASCII") from exc
    elements: list[_Element] = []
    fmt, comments = None, []
    for raw in lines:
        words = raw.split()
        if words[:1] == ["comment"]:
            comments.append(raw.split(None, 1)[1] if len(words) > 1 else "")
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and fmt is None:
            fmt = " ".join(words[1:])
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            if any(e.name == words[1] for e in elements):
                raise BadInputError(f"{source}: PLY element {words[1]!r} is declared twice")
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            element, name = elements[-1], words[-1]
            if name in element.order:
                raise BadInputError(f"{source}: PLY property {name!r} of element {element.name!r} is declared twice")
            if len(words) == 3 and words[1] in PLY_TYPES:
                element.scalars.append((name, PLY_TYPES[words[1]]))
            elif len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES and words[3] in PLY_TYPES:
                element.lists[name] = (PLY_TYPES[words[2]], PLY_TYPES[words[3]])
            else:
                raise BadInputError(f"{source}: unsupported PLY property line {raw!r}")
            element.order.append(name)
        else:
            raise BadInputError(f"{source}: unexpected PLY header line {raw!r}")
    if fmt != "binary_little_endian 1.0":
        raise BadInputError(f"{source}: PLY format {fmt!r}; only 'binary_little_endian 1.0' splats are read")
    return elements, newline + 1, comments


def _list_element_size(data: bytes, offset: int, element: _Element, source: Path) -> int:
    """Bytes taken by an element with list properties, walked row by row."""
    if element.count > MAX_LIST_ROWS:
        raise BadInputError(
            f"{source}: PLY element {element.name!r} has {element.count} rows, more than a splat file holds")
    start, types = offset, dict(element.scalars)
    for _ in range(element.count):
        for name in element.order:
            if name in types:
                offset += np.dtype(types[name]).itemsize
                continue
            count_type, item_type = (np.dtype(t) for t in element.lists[name])
            if offset + count_type.itemsize > len(data):
                raise BadInputError(f"{source}: truncated PLY body inside element {element.name!r}")
            n = int(np.frombuffer(data, count_type, count=1, offset=offset)[0])
            if n < 0:
                raise BadInputError(f"{source}: negative list length in PLY element {element.name!r}")
            offset += count_type.itemsize + n * item_type.itemsize
    return offset - start


def vertex_table(data: bytes, source: Path) -> tuple[np.ndarray, list[str]]:
    """(the `vertex` element as a structured array, the header's comments): the one validator every
    splat PLY reader uses."""
    elements, offset, comments = _header(data, source)
    vertex = [e for e in elements if e.name == "vertex"]
    if not vertex:
        raise BadInputError(f"{source}: PLY has no 'element vertex N'")
    if vertex[0].lists:
        raise BadInputError(f"{source}: PLY vertex element has list properties; splat properties are scalars")
    table = None
    for element in elements:
        if element.lists:
            offset += _list_element_size(data, offset, element, source)
            continue
        dtype = np.dtype(element.scalars)
        size = element.count * dtype.itemsize
        if offset + size > len(data):
            raise BadInputError(
                f"{source}: truncated PLY body: element {element.name!r} needs {size} bytes at offset {offset}, "
                f"the file holds {len(data)}"
            )
        if element is vertex[0]:
            table = np.frombuffer(data, dtype=dtype, count=element.count, offset=offset)
        offset += size
    if offset != len(data):
        raise BadInputError(
            f"{source}: PLY body is {len(data) - offset} bytes longer than its header promises "
            f"(element counts too small, or trailing data)"
        )
    return table, comments


def read_inria_ply(path: Path) -> Gaussians:
    path = Path(path)
    if not path.is_file():
        raise BadInputError(f"{path}: splat PLY does not exist")
    rows, comments = vertex_table(path.read_bytes(), path)
    if VIEWER_FRAME_COMMENT in comments:
        raise BadInputError(f"{path}: a shipped asset splat, written y-down for viewers; --splat takes a PLY in the "
                            "scan's turntable frame (+z up), such as another trainer's model of this scan")
    count, names = len(rows), list(rows.dtype.names)
    if count == 0:
        raise BadInputError(f"{path}: the PLY holds no splats ('element vertex 0')")
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise BadInputError(f"{path}: vertex lacks properties {missing}")

    def stack(keys: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([rows[k].astype(np.float32) for k in keys], axis=-1))

    rest = [f"f_rest_{i}" for i in range(sum(n.startswith("f_rest_") for n in names))]
    bases = len(rest) // 3 + 1
    if len(rest) % 3 or bases not in (1, 4, 9, 16) or not set(rest) <= set(names):
        raise BadInputError(f"{path}: {len(rest)} f_rest properties is not a whole SH degree")
    shN = stack(rest).reshape(count, 3, bases - 1).transpose(1, 2) if rest else torch.zeros(count, 0, 3)
    params = {
        "means": stack(["x", "y", "z"]),
        "scales": stack(["scale_0", "scale_1", "scale_2"]),
        "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        "opacities": torch.from_numpy(rows["opacity"].astype(np.float32)),
        "sh0": stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :],
        "shN": shN.contiguous(),
    }
    for name, value in params.items():
        if not bool(torch.isfinite(value).all()):
            raise BadInputError(f"{path}: property group {name} holds NaN or inf")
    if bool((params["quats"].norm(dim=-1) == 0).any()):
        raise BadInputError(f"{path}: a rotation quaternion is zero")
    return Gaussians(params)
