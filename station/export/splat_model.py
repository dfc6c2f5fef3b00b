"""The in-memory splat every writer and reader in this package exchanges.

Values are kept in the training parametrisation (log scales, logit opacity, SH coefficients),
exactly as INRIA PLY stores them, so a PLY round trip is lossless up to the frame's rotation. Each
format is written in its own axis convention (below) by rotating a copy with `SplatModel.rotated`,
which also rotates the view-dependent SH bands so colours seen from a given direction are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.errors import BadInputError
from station.ngs.conventions import SH_C0

# Each format's own frame, from the turntable frame (metres, origin the turntable centre on the
# plate, +z up); docs/formats.md has the table. All are proper rotations about the origin.
# INRIA PLY, antimatter15 .splat and SPZ: the y-down (COLMAP/OpenCV) frame 3DGS viewers assume.
TURNTABLE_TO_YDOWN = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
# glTF (+Y up): the PLY frame turned 180 degrees about z, as PlayCanvas' splat-transform maps it.
TURNTABLE_TO_YUP = np.diag([-1.0, -1.0, 1.0]) @ TURNTABLE_TO_YDOWN

_SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}


def sh_rest_count(degree: int) -> int:
    """Number of non-DC SH coefficients per channel for a degree (0..3)."""
    return _SH_REST_COUNTS[degree]


def sh_degree_for_rest(count: int) -> int | None:
    """Inverse of `sh_rest_count`; None when `count` matches no degree."""
    for degree, rest in _SH_REST_COUNTS.items():
        if rest == count:
            return degree
    return None


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    p = np.clip(p, eps, 1.0 - eps)
    return np.log(p / (1.0 - p))


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions; a zero quaternion becomes the identity rather than NaN."""
    q = np.asarray(q, dtype=np.float64)  # [N, 4]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    return out


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions, broadcasting."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """wxyz quaternion of one proper 3x3 rotation matrix."""
    w = np.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = np.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0
    y = np.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0
    z = np.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0
    x = np.copysign(x, r[2, 1] - r[1, 2])
    y = np.copysign(y, r[0, 2] - r[2, 0])
    z = np.copysign(z, r[1, 0] - r[0, 1])
    return quat_normalize(np.array([w, x, y, z]))


def sh_basis(dirs: np.ndarray, degree: int) -> list[np.ndarray]:
    """Real SH basis per band (1..degree) in the 3DGS/gsplat convention: list of [P, 2l+1]."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    bands = []
    if degree >= 1:
        bands.append(np.stack([-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x], 1))
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        bands.append(
            np.stack(
                [
                    1.0925484305920792 * x * y,
                    -1.0925484305920792 * y * z,
                    0.31539156525252005 * (2 * zz - xx - yy),
                    -1.0925484305920792 * x * z,
                    0.5462742152960396 * (xx - yy),
                ],
                1,
            )
        )
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        bands.append(
            np.stack(
                [
                    -0.5900435899266435 * y * (3 * xx - yy),
                    2.890611442640554 * x * y * z,
                    -0.4570457994644658 * y * (4 * zz - xx - yy),
                    0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                    -0.4570457994644658 * x * (4 * zz - xx - yy),
                    1.445305721320277 * z * (xx - yy),
                    -0.5900435899266435 * x * (xx - 3 * yy),
                ],
                1,
            )
        )
    return bands


def sh_rotation_matrices(rotation: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per band, the matrix A with c' = A c so that sum c'_k Y_k(d) = sum c_k Y_k(R^T d).

    Fitted by least squares on many directions: exact for real SH (each band is closed under
    rotation) and far shorter than Wigner-D recursions.
    """
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(256, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)  # [P, 3]
    rotated_dirs = dirs @ rotation  # rows are R^T d
    return [
        np.linalg.lstsq(y, y_rot, rcond=None)[0]
        for y, y_rot in zip(sh_basis(dirs, degree), sh_basis(rotated_dirs, degree))
    ]


@dataclass
class SplatModel:
    """N Gaussians in the training parametrisation; every array float32."""

    means: np.ndarray  # [N, 3] metres
    scales_log: np.ndarray  # [N, 3] log standard deviations
    quats: np.ndarray  # [N, 4] wxyz, not necessarily unit
    opacity_logit: np.ndarray  # [N]
    sh_dc: np.ndarray  # [N, 3]
    sh_rest: np.ndarray  # [N, K, 3], K in {0, 3, 8, 15}

    def __post_init__(self) -> None:
        for name in ("means", "scales_log", "quats", "opacity_logit", "sh_dc", "sh_rest"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (n, 3),
            "scales_log": (n, 3),
            "quats": (n, 4),
            "opacity_logit": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise BadInputError(f"SplatModel.{name}: shape {getattr(self, name).shape}, expected {shape}")
        rest = self.sh_rest
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or sh_degree_for_rest(rest.shape[1]) is None:
            raise BadInputError(f"SplatModel.sh_rest: shape {rest.shape}, expected [{n}, 0|3|8|15, 3]")
        for name in ("means", "scales_log", "quats", "opacity_logit", "sh_dc", "sh_rest"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise BadInputError(f"SplatModel.{name}: contains NaN or inf")

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(sh_degree_for_rest(self.sh_rest.shape[1]))

    def rgb(self) -> np.ndarray:
        """View-independent colour in [0, 1]: what viewers show for the DC band. [N, 3]"""
        return np.clip(0.5 + SH_C0 * self.sh_dc, 0.0, 1.0)

    def opacity(self) -> np.ndarray:
        return sigmoid(self.opacity_logit.astype(np.float64))  # [N]

    def subset(self, index: np.ndarray) -> "SplatModel":
        return SplatModel(
            self.means[index],
            self.scales_log[index],
            self.quats[index],
            self.opacity_logit[index],
            self.sh_dc[index],
            self.sh_rest[index],
        )

    def rotated(self, rotation: np.ndarray) -> "SplatModel":
        """The same splat expressed in a frame rotated by the proper rotation `rotation` (3x3)."""
        rotation = np.asarray(rotation, dtype=np.float64)
        if rotation.shape != (3, 3) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6):
            raise BadInputError(f"rotation must be a 3x3 orthonormal matrix, got {rotation.tolist()}")
        if np.linalg.det(rotation) < 0:
            raise BadInputError("rotation must be proper (det +1): a mirror would flip every splat's handedness")
        quats = quat_multiply(matrix_to_quat(rotation)[None, :], self.quats.astype(np.float64))
        rest = self.sh_rest.astype(np.float64)
        out = np.zeros_like(rest)
        start = 0
        for a in sh_rotation_matrices(rotation, self.sh_degree):
            k = a.shape[0]
            out[:, start : start + k] = np.einsum("ij,njc->nic", a, rest[:, start : start + k])
            start += k
        return SplatModel(
            self.means.astype(np.float64) @ rotation.T,
            self.scales_log,
            quats,
            self.opacity_logit,
            self.sh_dc,
            out,
        )
