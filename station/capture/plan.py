"""The scan plan: pure data, no I/O (bluesky's "plans are data, engines run them").

A plan lists every frame a scan must end with, in the order the session shoots them: first
one empty-turntable plate per elevation (the operator has not placed the stone yet), then the
stone shots, elevation by elevation, azimuth by azimuth. Tests compare `plan.frames()` with
what they expect; the session decides which of them still need shooting.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from station.errors import BadInputError

FrameKind = Literal["shot", "plate"]


def default_elevations(count: int = 6) -> tuple[float, ...]:
    """Evenly spread tilt angles over the upper hemisphere, avoiding grazing and top-down views."""
    return tuple(float(e) for e in np.round(np.linspace(10.0, 75.0, count), 3))


@dataclass(frozen=True)
class PlannedFrame:
    kind: FrameKind
    elevation_index: int
    elevation_deg: float
    azimuth_deg: float
    file: str  # relative to the scan folder


@dataclass(frozen=True)
class ScanPlan:
    """Which frames a scan takes, and with which camera settings."""

    elevations_deg: tuple[float, ...] = default_elevations()
    azimuths: int = 40
    exposure_s: float = 1.0 / 30.0
    iso: int = 100

    def __post_init__(self) -> None:
        if not self.elevations_deg:
            raise BadInputError("scan plan: at least one elevation is needed")
        if any(not -90.0 < e <= 90.0 for e in self.elevations_deg):
            raise BadInputError(f"scan plan: elevations must lie in (-90, 90] degrees, got {self.elevations_deg}")
        if self.azimuths < 1:
            raise BadInputError(f"scan plan: azimuth count must be >= 1, got {self.azimuths}")
        if self.exposure_s <= 0 or self.iso <= 0:
            raise BadInputError("scan plan: exposure and ISO must be positive")

    def azimuth_angles(self) -> list[float]:
        return [360.0 * j / self.azimuths for j in range(self.azimuths)]

    def plates(self) -> list[PlannedFrame]:
        return [PlannedFrame("plate", i, e, 0.0, f"raw/plate_e{i}.dng") for i, e in enumerate(self.elevations_deg)]

    def shots(self) -> list[PlannedFrame]:
        return [
            PlannedFrame("shot", i, e, a, f"raw/e{i}_a{j:03d}.dng")
            for i, e in enumerate(self.elevations_deg)
            for j, a in enumerate(self.azimuth_angles())
        ]

    def frames(self) -> list[PlannedFrame]:
        return self.plates() + self.shots()

    def to_dict(self) -> dict:
        data = asdict(self)
        data["elevations_deg"] = list(self.elevations_deg)
        return data

    @staticmethod
    def from_dict(data: dict) -> "ScanPlan":
        return ScanPlan(
            elevations_deg=tuple(float(e) for e in data["elevations_deg"]),
            azimuths=int(data["azimuths"]),
            exposure_s=float(data["exposure_s"]),
            iso=int(data["iso"]),
        )
