"""Niantic SPZ v3: a gzip-compressed, quantised splat, about a tenth of the PLY's size.

Follows nianticlabs/spz `load-spz.cc` (MIT). After gunzip: a 16-byte header
`magic u32 = 0x5053474e ("NGSP"), version u32, numPoints u32, shDegree u8, fractionalBits u8,
flags u8, reserved u8`, then attribute blocks for all points in this order:
positions (3 x 24-bit signed fixed point, `fractionalBits` fraction bits), alphas (u8 of
sigmoid(opacity)*255), colours (u8 of dc*0.15*255 + 0.5*255), scales (u8 of (log s + 10)*16),
rotations (v3: 4 bytes "smallest three": 2-bit index of the largest xyzw component, then three
10-bit fields of sign bit + 9-bit |q_i|/sqrt(1/2)), SH (u8 per coefficient, RGB interleaved per
coefficient, q = round(x*128)+128 rounded to 8-bucket (degree 1) or 16-bucket (higher) centres).
The file carries no frame: we write the y-down PLY convention, as PlayCanvas' splat-transform and
Spark read and write SPZ (without the RUB flip of Niantic's library), so an SPZ lands where our
splat.ply does in those viewers (docs/formats.md).
"""

from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.export.splat_model import (
    TURNTABLE_TO_YDOWN,
    SplatModel,
    logit,
    quat_normalize,
    sh_rest_count,
    sigmoid,
)

SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 3
FRACTIONAL_BITS = 12
COLOR_SCALE = 0.15
MAX_POINTS = 10_000_000  # the reference reader's own cap
_HEADER = struct.Struct("<IIIBBBB")
_SQRT1_2 = np.float64(0.7071067811865476)
_MASK9 = (1 << 9) - 1


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _pack_positions(means: np.ndarray) -> np.ndarray:
    fixed = np.round(means.astype(np.float64) * (1 << FRACTIONAL_BITS)).astype(np.int64)  # [N, 3]
    if np.any(np.abs(fixed) >= (1 << 23)):
        raise BadInputError(f"SPZ: positions beyond +-{(1 << 23) / (1 << FRACTIONAL_BITS):.0f} m cannot be stored")
    fixed &= 0xFFFFFF
    return np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=-1).astype(np.uint8)


def _unpack_positions(raw: np.ndarray, fractional_bits: int) -> np.ndarray:
    b = raw.astype(np.int64)  # [N, 3, 3]
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)  # sign extension
    return fixed.astype(np.float64) / (1 << fractional_bits)


def _pack_quats_smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    q = quat_normalize(quats_wxyz)[:, [1, 2, 3, 0]]  # [N, 4] xyzw, SPZ's order
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint64)
    for i in range(4):
        keep = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint64)
        mag = np.floor(_MASK9 * (np.abs(q[:, i]) / _SQRT1_2) + 0.5).astype(np.uint64)
        comp = np.where(keep, (comp << np.uint64(10)) | (negbit << np.uint64(9)) | mag, comp)
    comp = comp.astype(np.uint32)
    return np.stack([(comp >> s) & 0xFF for s in (0, 8, 16, 24)], axis=-1).astype(np.uint8)


def _unpack_quats_smallest_three(raw: np.ndarray) -> np.ndarray:
    comp = raw[:, 0].astype(np.uint32) | (raw[:, 1].astype(np.uint32) << 8)
    comp |= (raw[:, 2].astype(np.uint32) << 16) | (raw[:, 3].astype(np.uint32) << 24)
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((len(raw), 4))
    for i in (3, 2, 1, 0):
        skip = largest == i
        mag = (comp & _MASK9).astype(np.float64)
        neg = ((comp >> 9) & 1).astype(bool)
        value = _SQRT1_2 * mag / _MASK9
        q[:, i] = np.where(skip, 0.0, np.where(neg, -value, value))
        comp = np.where(skip, comp, comp >> 10)
    rows = np.arange(len(raw))
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, axis=1)))
    return q[:, [3, 0, 1, 2]]  # wxyz


def _unpack_quats_first_three(raw: np.ndarray) -> np.ndarray:
    xyz = raw.astype(np.float64) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))
    return np.concatenate([w[:, None], xyz], axis=1)


def _quantize_sh(x: np.ndarray, bucket: int) -> np.ndarray:
    q = np.round(x.astype(np.float64) * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def encode_spz(model: SplatModel) -> bytes:
    """gzip'd SPZ v3 bytes of a turntable-frame model."""
    m = model.rotated(TURNTABLE_TO_YDOWN)
    n, k = m.num, m.sh_rest.shape[1]
    header = _HEADER.pack(SPZ_MAGIC, SPZ_VERSION, n, m.sh_degree, FRACTIONAL_BITS, 0, 0)
    sh = np.zeros((n, k, 3), np.uint8)
    if k:
        sh[:, :3] = _quantize_sh(m.sh_rest[:, :3], bucket=1 << (8 - 5))
        sh[:, 3:] = _quantize_sh(m.sh_rest[:, 3:], bucket=1 << (8 - 4))
    blocks = [
        _pack_positions(m.means),
        _u8(sigmoid(m.opacity_logit.astype(np.float64)) * 255.0),
        _u8(m.sh_dc.astype(np.float64) * (COLOR_SCALE * 255.0) + 0.5 * 255.0),
        _u8((m.scales_log.astype(np.float64) + 10.0) * 16.0),
        _pack_quats_smallest_three(m.quats),
        sh,
    ]
    return gzip.compress(header + b"".join(b.tobytes() for b in blocks), compresslevel=6, mtime=0)


def decode_spz(data: bytes, source: Path) -> SplatModel:
    """Turntable-frame model of SPZ (v2 or v3) bytes; BadInputError naming `source` otherwise."""
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as exc:
        raise BadInputError(f"{source}: not a readable gzip stream, so not SPZ ({exc})") from exc
    if len(raw) < _HEADER.size:
        raise BadInputError(f"{source}: SPZ shorter than its 16-byte header")
    magic, version, n, degree, frac, flags, _ = _HEADER.unpack_from(raw)
    if magic != SPZ_MAGIC:
        raise BadInputError(f"{source}: bad SPZ magic 0x{magic:08x}, expected 0x{SPZ_MAGIC:08x} ('NGSP')")
    if version not in (2, 3):
        raise BadInputError(f"{source}: SPZ version {version} unsupported (reads 2 and 3)")
    if n > MAX_POINTS or degree > 3 or frac > 23:
        raise BadInputError(f"{source}: implausible SPZ header (points {n}, SH degree {degree}, fraction bits {frac})")
    if flags & 0x2:
        raise BadInputError(f"{source}: SPZ extensions are not supported")
    k = sh_rest_count(degree)
    rot_bytes = 4 if version >= 3 else 3
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k * n]
    if len(raw) < _HEADER.size + sum(sizes):
        raise BadInputError(f"{source}: truncated SPZ: {n} points need {_HEADER.size + sum(sizes)} bytes, got {len(raw)}")
    body = np.frombuffer(raw, dtype=np.uint8, offset=_HEADER.size, count=sum(sizes))
    pos, alpha, color, scale, rot, sh = np.split(body, np.cumsum(sizes)[:-1])
    quats = (
        _unpack_quats_smallest_three(rot.reshape(n, 4))
        if version >= 3
        else _unpack_quats_first_three(rot.reshape(n, 3))
    )
    model = SplatModel(
        means=_unpack_positions(pos.reshape(n, 3, 3), frac),
        scales_log=scale.reshape(n, 3).astype(np.float64) / 16.0 - 10.0,
        quats=quats,
        opacity_logit=logit(alpha.astype(np.float64) / 255.0, eps=0.5 / 255.0),
        sh_dc=(color.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE,
        sh_rest=(sh.reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0,
    )
    return model.rotated(TURNTABLE_TO_YDOWN.T)
