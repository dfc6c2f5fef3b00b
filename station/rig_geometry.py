"""Nominal rig geometry: where the camera is, in the turntable frame, for a (tilt, turn) pose.

The turntable frame rotates with the plate: origin on the turntable axis at the plate surface,
+z up, metres. The camera rides a tilt arm that pivots about a horizontal lab axis through the
aim point (0, 0, aim_height) and always looks at it. At tilt (elevation) `e` the lab-frame
camera centre is aim + R·(cos e, 0, sin e). Turning the plate by `a` degrees (counter-clockwise
seen from above) is the same as the camera orbiting by -a in the turntable frame.

This is the rig model every stage shares: the simulator renders with it, capture records it in
scan.json, and process uses it as the prior it calibrates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class RigGeometry:
    """Physical layout of a station (metres, pixels)."""

    orbit_radius_m: float = 0.45
    aim_height_m: float = 0.04
    width: int = 320
    height: int = 240
    focal_px: float = 560.0  # about a 32 deg horizontal field at 320 px: a 10 cm stone fills half

    def intrinsics(self) -> np.ndarray:
        """3x3 pinhole K with the principal point at the image centre."""
        return np.array(
            [[self.focal_px, 0.0, self.width / 2.0], [0.0, self.focal_px, self.height / 2.0], [0.0, 0.0, 1.0]]
        )

    def scaled(self, width: int, height: int) -> "RigGeometry":
        """The same rig seen at another resolution (focal length scales with width)."""
        return RigGeometry(
            orbit_radius_m=self.orbit_radius_m,
            aim_height_m=self.aim_height_m,
            width=width,
            height=height,
            focal_px=self.focal_px * width / self.width,
        )

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(data: dict) -> "RigGeometry":
        return RigGeometry(**{k: data[k] for k in RigGeometry.__dataclass_fields__ if k in data})


def look_at_c2w(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) for a camera at `eye` looking at `target`."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight down or up: any right vector will do
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def rotation_z(degrees: float) -> np.ndarray:
    t = np.deg2rad(degrees)
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_to_turntable(elevation_deg: float, azimuth_deg: float, rig: RigGeometry) -> np.ndarray:
    """4x4 OpenCV camera-to-world pose in the turntable frame for tilt `elevation_deg` and turn `azimuth_deg`."""
    e = np.deg2rad(elevation_deg)
    aim = np.array([0.0, 0.0, rig.aim_height_m])
    eye_lab = aim + rig.orbit_radius_m * np.array([np.cos(e), 0.0, np.sin(e)])
    c2w_lab = look_at_c2w(eye_lab, aim)
    turn = np.eye(4)
    turn[:3, :3] = rotation_z(-azimuth_deg)
    return turn @ c2w_lab


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Flip a camera-to-world pose from OpenCV (y down, z forward) to OpenGL/nerfstudio (y up, z back)."""
    flipped = c2w.copy()
    flipped[:3, 1:3] *= -1.0
    return flipped
