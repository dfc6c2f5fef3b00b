"""antimatter15 `.splat`: the 32-byte-per-splat format most web viewers open.

Layout per splat (little-endian): 3 x f32 position, 3 x f32 linear scale, 4 x u8 RGBA with
rgb = 0.5 + C0*f_dc and a = sigmoid(opacity), 4 x u8 quaternion q*128+128 in w,x,y,z order,
normalised. No header and no view-dependent colour. Viewers expect the splats sorted by
importance (size times opacity, largest first) so a partial download already looks right.
The file is written in the y-down frame of the PLY convention (as our splat.ply), so the stone
stands upright in 3DGS viewers; the reader rotates back to the turntable frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.export.splat_model import (
    SH_C0,
    TURNTABLE_TO_YDOWN,
    SplatModel,
    logit,
    quat_normalize,
)

SPLAT_DTYPE = np.dtype(
    [("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)]
)


def splat_order(model: SplatModel) -> np.ndarray:
    """Importance order viewers expect: volume (exp of summed log scales) x opacity, descending."""
    importance = np.exp(model.scales_log.astype(np.float64).sum(axis=1)) * model.opacity()
    return np.argsort(-importance, kind="stable")


def encode_splat(model: SplatModel) -> bytes:
    """Sorted, y-down `.splat` bytes of a turntable-frame model."""
    m = model.rotated(TURNTABLE_TO_YDOWN).subset(splat_order(model))
    records = np.zeros(m.num, dtype=SPLAT_DTYPE)
    records["position"] = m.means
    records["scale"] = np.exp(m.scales_log)
    rgb = np.clip(np.round(m.rgb() * 255.0), 0, 255)
    alpha = np.clip(np.round(m.opacity() * 255.0), 0, 255)
    records["rgba"] = np.concatenate([rgb, alpha[:, None]], axis=1).astype(np.uint8)
    q = quat_normalize(m.quats)
    records["rot"] = np.clip(np.round(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return records.tobytes()


def decode_splat(data: bytes, source: Path) -> SplatModel:
    """Turntable-frame model of `.splat` bytes (SH degree 0: the format stores no more)."""
    if len(data) == 0 or len(data) % SPLAT_DTYPE.itemsize:
        raise BadInputError(
            f"{source}: {len(data)} bytes is not a whole number of 32-byte .splat records (truncated or not a .splat)"
        )
    records = np.frombuffer(data, dtype=SPLAT_DTYPE)
    finite = np.all(np.isfinite(records["position"])) and np.all(np.isfinite(records["scale"]))
    if not finite or np.any(records["scale"] <= 0):
        raise BadInputError(f"{source}: .splat holds non-finite positions or non-positive scales (garbage data)")
    scale = records["scale"].astype(np.float64)
    rgba = records["rgba"].astype(np.float64) / 255.0
    q = (records["rot"].astype(np.float64) - 128.0) / 128.0
    if np.any(np.linalg.norm(q, axis=1) < 0.5):
        raise BadInputError(f"{source}: .splat holds quaternions far from unit length (garbage data)")
    model = SplatModel(
        means=records["position"],
        scales_log=np.log(scale),
        quats=quat_normalize(q),
        opacity_logit=logit(rgba[:, 3], eps=0.5 / 255.0),
        sh_dc=(rgba[:, :3] - 0.5) / SH_C0,
        sh_rest=np.zeros((len(records), 0, 3), np.float32),
    )
    return model.rotated(TURNTABLE_TO_YDOWN.T)
