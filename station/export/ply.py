"""INRIA 3DGS PLY: the layout every splat viewer and trainer reads.

Spec, as written by the reference implementation: binary little-endian, one `vertex` element,
float32 properties `x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3` with
M = 3*((d+1)^2-1). `f_rest` is channel-major (all R coefficients, then G, then B), opacity is a
logit, scales are logs and `rot` is wxyz, unnormalised. The reader accepts the properties in any
order (other trainers reorder them) but refuses anything it cannot map exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.export.splat_model import SplatModel, sh_degree_for_rest
from station.scanfolder import atomic_write_bytes

MAX_HEADER_BYTES = 65536
_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def ply_property_names(sh_degree: int) -> list[str]:
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return _BASE + [f"f_rest_{i}" for i in range(rest)] + _TAIL


def encode_ply(model: SplatModel, comment: str | None = None) -> bytes:
    names = ply_property_names(model.sh_degree)
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header.append(f"element vertex {model.num}")
    header += [f"property float {name}" for name in names]
    header.append("end_header")
    rest = model.sh_rest.transpose(0, 2, 1).reshape(model.num, -1)  # [N, 3*K] channel-major
    body = np.concatenate(
        [
            model.means,
            np.zeros((model.num, 3), np.float32),
            model.sh_dc,
            rest,
            model.opacity_logit[:, None],
            model.scales_log,
            model.quats,
        ],
        axis=1,
    ).astype("<f4")  # [N, P]
    return ("\n".join(header) + "\n").encode("ascii") + body.tobytes()


def write_ply(path: Path, model: SplatModel, comment: str | None = None) -> None:
    """Write `model` as INRIA PLY, atomically (temp file + rename)."""
    atomic_write_bytes(Path(path), encode_ply(model, comment))


def _parse_header(data: bytes, source: Path) -> tuple[int, list[str], int]:
    """(vertex count, property names, byte offset of the body); refuses what we cannot read."""
    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise BadInputError(f"{source}: not a PLY file (no 'ply' magic line)")
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise BadInputError(f"{source}: PLY header has no end_header within {MAX_HEADER_BYTES} bytes")
    newline = data.find(b"\n", end)
    if newline < 0:
        raise BadInputError(f"{source}: PLY header ends without a newline after end_header (truncated)")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as exc:
        raise BadInputError(f"{source}: PLY header is not ASCII") from exc
    count, names, elements, fmt = None, [], 0, None
    for raw in lines:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = " ".join(words[1:])
        elif words[0] == "element":
            elements += 1
            if len(words) != 3 or words[1] != "vertex" or not words[2].isdigit():
                raise BadInputError(f"{source}: unexpected PLY element line {raw!r}; a splat has one 'element vertex N'")
            count = int(words[2])
        elif words[0] == "property":
            # "property float x": only scalar float32 properties are part of the splat layout.
            if len(words) != 3 or words[1] not in ("float", "float32"):
                raise BadInputError(f"{source}: unsupported PLY property {raw!r}; splat properties are float")
            names.append(words[2])
        else:
            raise BadInputError(f"{source}: unexpected PLY header line {raw!r}")
    if fmt != "binary_little_endian 1.0":
        raise BadInputError(f"{source}: PLY format {fmt!r}; expected 'binary_little_endian 1.0'")
    if elements != 1 or count is None:
        raise BadInputError(f"{source}: PLY must have exactly one vertex element")
    if len(set(names)) != len(names):
        raise BadInputError(f"{source}: PLY has duplicate property names")
    return count, names, newline + 1


def decode_ply(data: bytes, source: Path) -> SplatModel:
    count, names, offset = _parse_header(data, source)
    required = set(_BASE[:3] + ["f_dc_0", "f_dc_1", "f_dc_2"] + _TAIL)
    missing = sorted(required - set(names))
    if missing:
        raise BadInputError(f"{source}: not a Gaussian-splat PLY, missing properties {missing}")
    rest_names = [n for n in names if n.startswith("f_rest_")]
    degree = sh_degree_for_rest(len(rest_names) // 3) if len(rest_names) % 3 == 0 else None
    if degree is None or set(rest_names) != {f"f_rest_{i}" for i in range(len(rest_names))}:
        raise BadInputError(f"{source}: {len(rest_names)} f_rest properties match no SH degree 0..3")
    expected = count * len(names) * 4
    available = len(data) - offset
    if available < expected:
        raise BadInputError(
            f"{source}: truncated PLY body: header promises {count} splats ({expected} bytes), file holds {available}"
        )
    table = np.frombuffer(data, dtype="<f4", count=count * len(names), offset=offset).reshape(count, len(names))
    col = {name: i for i, name in enumerate(names)}

    def take(*keys: str) -> np.ndarray:
        return table[:, [col[k] for k in keys]].astype(np.float32)

    k = len(rest_names) // 3
    rest = take(*[f"f_rest_{i}" for i in range(3 * k)]).reshape(count, 3, k).transpose(0, 2, 1)
    try:
        return SplatModel(
            means=take("x", "y", "z"),
            scales_log=take("scale_0", "scale_1", "scale_2"),
            quats=take("rot_0", "rot_1", "rot_2", "rot_3"),
            opacity_logit=take("opacity")[:, 0],
            sh_dc=take("f_dc_0", "f_dc_1", "f_dc_2"),
            sh_rest=rest,
        )
    except BadInputError as exc:
        raise BadInputError(f"{source}: {exc}") from exc


def read_ply(path: Path) -> SplatModel:
    """Read an INRIA splat PLY; BadInputError naming the file on anything malformed."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BadInputError(f"{path}: cannot read splat PLY ({exc.strerror})") from exc
    return decode_ply(data, path)
