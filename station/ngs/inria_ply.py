"""A minimal reader of INRIA-layout splat PLYs, so `station sos --splat` can score foreign models.

Layout (binary little-endian float32 per vertex): x y z, [nx ny nz], f_dc_0..2, f_rest_0..(3K-4),
opacity (logit), scale_0..2 (log), rot_0..3 (wxyz). f_rest is channel-major: all R coefficients,
then all G, then all B. The file is untrusted: sizes are checked before anything is allocated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from station.errors import BadInputError
from station.ngs.gaussians import Gaussians

PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
             "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4", "short": "<i2", "ushort": "<u2"}
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
MAX_HEADER = 64 * 1024


def read_inria_ply(path: Path) -> Gaussians:
    path = Path(path)
    if not path.is_file():
        raise BadInputError(f"{path}: splat PLY does not exist")
    data = path.read_bytes()
    end = data.find(b"end_header\n", 0, MAX_HEADER)
    if not data.startswith(b"ply\n") or end < 0:
        raise BadInputError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[end + len(b"end_header\n") :]
    if "format binary_little_endian 1.0" not in header:
        raise BadInputError(f"{path}: only binary_little_endian PLY splats are supported")
    count, fields, in_vertex = -1, [], False
    for line in header:
        words = line.split()
        if words[:2] == ["element", "vertex"] and len(words) == 3 and words[2].isdigit():
            count, in_vertex = int(words[2]), True
        elif words[:1] == ["element"]:
            in_vertex = False
        elif words[:1] == ["property"] and in_vertex:
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise BadInputError(f"{path}: unsupported vertex property line {line!r}")
            fields.append((words[2], PLY_TYPES[words[1]]))
    if count <= 0:
        raise BadInputError(f"{path}: no 'element vertex N' with N > 0")
    names = [name for name, _ in fields]
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise BadInputError(f"{path}: vertex lacks properties {missing}")
    dtype = np.dtype(fields)
    if len(body) < count * dtype.itemsize:
        raise BadInputError(f"{path}: truncated: {count} vertices need {count * dtype.itemsize} bytes, found {len(body)}")
    rows = np.frombuffer(body, dtype=dtype, count=count)

    def stack(keys: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([rows[k].astype(np.float32) for k in keys], axis=-1))

    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    bases = len(rest) // 3 + 1
    if len(rest) % 3 or bases not in (1, 4, 9, 16):
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
