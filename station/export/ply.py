"""INRIA 3DGS PLY: the layout every splat viewer and trainer reads.

Spec, as written by the reference implementation: binary little-endian, one `vertex` element,
float32 properties `x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3` with
M = 3*((d+1)^2-1). `f_rest` is channel-major (all R coefficients, then G, then B), opacity is a
logit, scales are logs and `rot` is wxyz, unnormalised. The file is written in the y-down frame of
3DGS viewers (docs/formats.md) and rotated back to the turntable frame on reading. The header and
byte count are checked by station.ngs.inria_ply, the one splat-PLY validator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.export.splat_model import TURNTABLE_TO_YDOWN, SplatModel, sh_degree_for_rest
from station.ngs.inria_ply import VIEWER_FRAME_COMMENT, vertex_table
_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def ply_property_names(sh_degree: int) -> list[str]:
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return _BASE + [f"f_rest_{i}" for i in range(rest)] + _TAIL


def encode_ply(model: SplatModel) -> bytes:
    """INRIA PLY bytes of a turntable-frame model, written y-down."""
    model = model.rotated(TURNTABLE_TO_YDOWN)
    names = ply_property_names(model.sh_degree)
    header = ["ply", "format binary_little_endian 1.0", f"comment {VIEWER_FRAME_COMMENT}"]
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


def decode_ply(data: bytes, source: Path) -> SplatModel:
    """Turntable-frame model of INRIA PLY bytes; BadInputError naming `source` otherwise."""
    table, _ = vertex_table(data, source)
    names = list(table.dtype.names)
    missing = sorted(set(_BASE[:3] + _BASE[6:] + _TAIL) - set(names))
    if missing:
        raise BadInputError(f"{source}: not a Gaussian-splat PLY, missing properties {missing}")
    rest_names = [n for n in names if n.startswith("f_rest_")]
    degree = sh_degree_for_rest(len(rest_names) // 3) if len(rest_names) % 3 == 0 else None
    if degree is None or set(rest_names) != {f"f_rest_{i}" for i in range(len(rest_names))}:
        raise BadInputError(f"{source}: {len(rest_names)} f_rest properties match no SH degree 0..3")
    count, k = len(table), len(rest_names) // 3

    def take(*keys: str) -> np.ndarray:
        columns = [table[key].astype(np.float32) for key in keys]
        return np.stack(columns, axis=-1) if columns else np.zeros((count, 0), np.float32)

    rest = take(*[f"f_rest_{i}" for i in range(3 * k)]).reshape(count, 3, k).transpose(0, 2, 1)
    try:
        model = SplatModel(
            means=take("x", "y", "z"),
            scales_log=take("scale_0", "scale_1", "scale_2"),
            quats=take("rot_0", "rot_1", "rot_2", "rot_3"),
            opacity_logit=take("opacity")[:, 0],
            sh_dc=take("f_dc_0", "f_dc_1", "f_dc_2"),
            sh_rest=rest,
        )
    except BadInputError as exc:
        raise BadInputError(f"{source}: {exc}") from exc
    return model.rotated(TURNTABLE_TO_YDOWN.T)
