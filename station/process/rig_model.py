"""The station's rig model: the turntable axis plus the camera pose at each elevation.

A turntable scan has only a handful of distinct camera poses (one per tilt); every other view
is the same pose turned about one axis. So the station is calibrated once, from a full SfM
scan, and every later scan is posed from the model: metric, in the turntable frame, and
immune to the backdrop that confuses per-scan SfM. Before calibration the nominal model from
scan.json's `RigGeometry` stands in.

Poses are OpenCV camera-to-world 4x4 matrices in the turntable frame (origin on the axis at
the plate surface, +z up, metres). Turning the plate by `a` degrees (counter-clockwise from
above) moves the camera by -a about the axis in that frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.errors import BadInputError
from station.process.lens import Lens
from station.formats.transforms import PinholeCamera
from station.rig_geometry import RigGeometry, camera_to_turntable
from station.scanfolder import atomic_write_json

ELEVATION_TOLERANCE_DEG = 0.05
FORMAT_VERSION = 1


def axis_rotation(axis_point: np.ndarray, axis_dir: np.ndarray, degrees: float) -> np.ndarray:
    """4x4 rigid rotation by `degrees` (right-handed) about the line through `axis_point` along `axis_dir`."""
    d = axis_dir / np.linalg.norm(axis_dir)
    t = np.deg2rad(degrees)
    k = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    rot = np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * (k @ k)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = axis_point - rot @ axis_point
    return out


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations [N, 3, 3]: the nearest rotation to their sum."""
    u, _, vt = np.linalg.svd(rotations.sum(axis=0))
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ fix @ vt


def rotation_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle of r_a^T r_b; from the chordal distance |r_a - r_b|_F = 2 sqrt(2) sin(angle / 2),
    which unlike arccos of the trace stays exact for tiny angles."""
    chord = np.linalg.norm(r_a - r_b) / (2.0 * np.sqrt(2.0))
    return float(np.rad2deg(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0))))


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 over points [N, 3] (Umeyama 1991)."""
    if len(src) < 3:
        raise BadInputError(f"similarity alignment needs at least 3 cameras, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, sig, vt = np.linalg.svd(cov)
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ fix @ vt
    var = (xs**2).sum() / len(src)
    if var <= 0.0:
        raise BadInputError("similarity alignment: all cameras at one point")
    scale = float(np.trace(np.diag(sig) @ fix) / var)
    return scale, rot, mu_d - scale * rot @ mu_s


def apply_similarity(c2w: np.ndarray, scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Move a camera-to-world pose by the world similarity x -> s R x + t (camera axes stay orthonormal)."""
    out = np.eye(4)
    out[:3, :3] = rot @ c2w[:3, :3]
    out[:3, 3] = scale * rot @ c2w[:3, 3] + trans
    return out


@dataclass(frozen=True)
class RigModel:
    """Turntable axis and the azimuth-zero camera pose per elevation, with the intrinsics they go with."""

    intrinsics: PinholeCamera
    elevation_poses: dict[float, np.ndarray]  # elevation_deg -> [4, 4] OpenCV c2w at azimuth 0
    axis_point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis_dir: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    kind: str = "nominal"
    residuals: dict[str, float] = field(default_factory=dict)
    distortion: Lens | None = None  # the lens self-calibration found (at `intrinsics`); None: pinhole, unrefined

    def __post_init__(self) -> None:
        if self.distortion is not None and self.distortion.intrinsics != self.intrinsics:
            raise BadInputError(f"rig model ({self.kind}): the lens's intrinsics differ from the model's")

    def lens(self) -> Lens:
        """The camera posing starts from: the calibrated lens, else the nominal pinhole."""
        return self.distortion if self.distortion is not None else Lens(self.intrinsics)

    @staticmethod
    def nominal(rig: RigGeometry, elevations_deg: list[float]) -> "RigModel":
        """The design geometry from scan.json, used until the station has been calibrated."""
        k = rig.intrinsics()
        intr = PinholeCamera(rig.width, rig.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        poses = {float(e): camera_to_turntable(float(e), 0.0, rig) for e in elevations_deg}
        return RigModel(intrinsics=intr, elevation_poses=poses)

    def _elevation_pose(self, elevation_deg: float) -> np.ndarray:
        for e, pose in self.elevation_poses.items():
            if abs(e - elevation_deg) <= ELEVATION_TOLERANCE_DEG:
                return pose
        known = ", ".join(f"{e:g}" for e in sorted(self.elevation_poses))
        raise BadInputError(f"rig model ({self.kind}): elevation {elevation_deg:g} deg not calibrated (has {known})")

    def camera_to_world(self, elevation_deg: float, azimuth_deg: float) -> np.ndarray:
        """4x4 OpenCV c2w in the turntable frame: the plate turned by +a moves the camera by -a."""
        return axis_rotation(self.axis_point, self.axis_dir, -azimuth_deg) @ self._elevation_pose(elevation_deg)

    def orbit_radius(self) -> float:
        """Mean distance of the cameras from the axis (the scale errors are quoted against)."""
        d = self.axis_dir / np.linalg.norm(self.axis_dir)
        radii = []
        for pose in self.elevation_poses.values():
            v = pose[:3, 3] - self.axis_point
            radii.append(np.linalg.norm(v - (v @ d) * d))
        return float(np.mean(radii))

    def to_dict(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "kind": self.kind,
            "intrinsics": vars(self.intrinsics),
            "axis_point": self.axis_point.tolist(),
            "axis_dir": self.axis_dir.tolist(),
            "elevations": [{"elevation_deg": e, "c2w": p.tolist()} for e, p in sorted(self.elevation_poses.items())],
            "residuals": self.residuals,
            **({"lens": self.distortion.to_dict()} if self.distortion is not None else {}),
        }

    @staticmethod
    def from_dict(data: dict, source: str = "rig model") -> "RigModel":
        try:
            intr = PinholeCamera(**{k: data["intrinsics"][k] for k in ("width", "height", "fx", "fy", "cx", "cy")})
            poses = {float(e["elevation_deg"]): np.asarray(e["c2w"], dtype=np.float64) for e in data["elevations"]}
            axis_point = np.asarray(data["axis_point"], dtype=np.float64)
            axis_dir = np.asarray(data["axis_dir"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise BadInputError(f"{source}: malformed rig model ({exc!r})") from exc
        if any(p.shape != (4, 4) or not np.isfinite(p).all() for p in poses.values()):
            raise BadInputError(f"{source}: every elevation 'c2w' must be a finite 4x4 matrix")
        if axis_point.shape != (3,) or axis_dir.shape != (3,) or np.linalg.norm(axis_dir) < 1e-9:
            raise BadInputError(f"{source}: 'axis_point' and 'axis_dir' must be 3-vectors, axis_dir non-zero")
        lens = data.get("lens")
        if lens is not None and not isinstance(lens, dict):
            raise BadInputError(f"{source}: 'lens' must be an object")
        return RigModel(intr, poses, axis_point, axis_dir, str(data.get("kind", "calibrated")),
                        {str(k): float(v) for k, v in data.get("residuals", {}).items()},
                        None if lens is None else Lens.from_dict(intr, lens, f"{source}: lens"))

    def save(self, path: Path) -> None:
        atomic_write_json(Path(path), self.to_dict())

    @staticmethod
    def load(path: Path) -> "RigModel":
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise BadInputError(f"{path}: cannot read rig model ({exc})") from exc
        if not isinstance(data, dict):
            raise BadInputError(f"{path}: rig model must be a JSON object")
        return RigModel.from_dict(data, str(path))


@dataclass(frozen=True)
class PosedView:
    """One view of a calibration scan: where the plan put it, and where SfM found it."""

    elevation_deg: float
    azimuth_deg: float
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world in the SfM frame (any gauge)


def calibrate_rig(views: list[PosedView], nominal: RigModel, lens: Lens | None = None) -> RigModel:
    """Fit the axis and the per-elevation poses to SfM poses of one full scan.

    The SfM gauge (scale, rotation, origin) is fixed by a similarity onto the nominal cameras,
    so the model stays metric and keeps the plate-surface origin; everything else (axis tilt
    and offset, true tilt angles, arm length, camera roll) comes from the images, and so does
    `lens` (self-calibrated intrinsics and distortion, at the developed images' size) when given.
    """
    if len(views) < 6:
        raise BadInputError(f"rig calibration: needs at least 6 registered views, got {len(views)}")
    nominal_c = np.array([nominal.camera_to_world(v.elevation_deg, v.azimuth_deg)[:3, 3] for v in views])
    sfm_c = np.array([v.c2w[:3, 3] for v in views])
    scale, rot, trans = umeyama(sfm_c, nominal_c)
    aligned = [apply_similarity(v.c2w, scale, rot, trans) for v in views]

    rings: dict[float, list[int]] = {}
    for i, v in enumerate(views):
        rings.setdefault(round(v.elevation_deg, 3), []).append(i)
    normals, centres = [], []
    for idx in rings.values():
        if len(idx) < 3:
            continue
        pts = np.array([aligned[i][:3, 3] for i in idx])
        normal, centre = _fit_circle_axis(pts)
        normals.append(normal if normal[2] >= 0 else -normal)
        centres.append(centre)
    if not normals:
        raise BadInputError("rig calibration: no elevation ring has 3 or more registered views")
    axis_dir = np.mean(normals, axis=0)
    axis_dir /= np.linalg.norm(axis_dir)
    # The axis point nearest the nominal origin keeps "z = 0 at the plate surface".
    centres_arr = np.array(centres)
    axis_point = centres_arr.mean(0) - (centres_arr.mean(0) @ axis_dir) * axis_dir

    # Re-express in a frame whose z is the fitted axis, so the model is a plain z-turn again.
    x = np.array([1.0, 0.0, 0.0]) - axis_dir[0] * axis_dir
    x /= np.linalg.norm(x)
    frame = np.stack([x, np.cross(axis_dir, x), axis_dir])  # rows: new axes in the old frame
    to_canon = np.eye(4)
    to_canon[:3, :3] = frame
    to_canon[:3, 3] = -frame @ axis_point
    canon = [to_canon @ p for p in aligned]

    elevation_poses = {}
    for e, idx in rings.items():
        unturned = [axis_rotation(np.zeros(3), np.array([0.0, 0.0, 1.0]), views[i].azimuth_deg) @ canon[i] for i in idx]
        pose = np.eye(4)
        pose[:3, :3] = mean_rotation(np.array([u[:3, :3] for u in unturned]))
        pose[:3, 3] = np.mean([u[:3, 3] for u in unturned], axis=0)
        elevation_poses[float(e)] = pose
    model = RigModel(nominal.intrinsics, elevation_poses, np.zeros(3), np.array([0.0, 0.0, 1.0]), "calibrated")

    rot_err = [rotation_angle_deg(model.camera_to_world(v.elevation_deg, v.azimuth_deg)[:3, :3], c[:3, :3])
               for v, c in zip(views, canon)]
    ctr_err = [np.linalg.norm(model.camera_to_world(v.elevation_deg, v.azimuth_deg)[:3, 3] - c[:3, 3])
               for v, c in zip(views, canon)]
    tilt = float(np.rad2deg(np.arccos(np.clip(axis_dir[2], -1.0, 1.0))))
    residuals = {
        "views": float(len(views)),
        "rotation_median_deg": float(np.median(rot_err)),
        "centre_median_m": float(np.median(ctr_err)),
        "axis_tilt_from_nominal_deg": tilt,
        "axis_offset_from_nominal_m": float(np.linalg.norm(axis_point)),
        "sfm_to_metric_scale": scale,
    }
    intr = lens.intrinsics if lens is not None else model.intrinsics
    return RigModel(intr, elevation_poses, model.axis_point, model.axis_dir, "calibrated", residuals, lens)


def _fit_circle_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane normal and circle centre of points [N, 3] lying on one ring."""
    mu = points.mean(0)
    _, _, vt = np.linalg.svd(points - mu)
    normal = vt[2]
    e1, e2 = vt[0], vt[1]
    uv = np.stack([(points - mu) @ e1, (points - mu) @ e2], 1)  # [N, 2]
    # Algebraic circle fit: u^2 + v^2 = 2 a u + 2 b v + c.
    a_mat = np.column_stack([2 * uv, np.ones(len(uv))])
    sol, *_ = np.linalg.lstsq(a_mat, (uv**2).sum(1), rcond=None)
    return normal, mu + sol[0] * e1 + sol[1] * e2
