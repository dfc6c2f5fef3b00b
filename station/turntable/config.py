"""What the rig expects of its turntable board, and how long to wait for it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from station.errors import BadInputError
from station.turntable.planning import Rotation


@dataclass
class TurntableConfig:
    """What the rig expects of its board, and how long to wait for it."""

    steps_per_deg: tuple[float, float] = (44.444, 44.444)  # $100, $101: a wrong value mis-scales every angle
    max_rate_deg_min: tuple[float, float] = (3600.0, 1800.0)  # $110, $111
    accel_deg_s2: tuple[float, float] = (180.0, 90.0)  # $120, $121
    settings_rel_tol: float = 1e-3
    feed_deg_min: float = 1800.0
    tilt_limits_deg: tuple[float, float] = (0.0, 90.0)
    tilt_axis: Literal["Y", "A"] = "Y"
    rotation: Rotation = "shortest"
    x_range_deg: tuple[float, float] = (-360.0, 360.0)  # work X stays here: targets wrap by whole turns
    baudrate: int = 115200
    banner_timeout_s: float = 3.0
    banner_retry_s: float = 1.0  # a board just powered up ignores the first reset: send another
    reply_timeout_s: float = 2.0
    poll_hz: float = 4.0  # status fallback while waiting for motion; GRBL advises 5 Hz at most
    motion_margin_s: float = 2.0
    home_timeout_s: float = 120.0
    reconnect_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if not 0 < self.poll_hz <= 5:
            raise BadInputError(f"TurntableConfig.poll_hz={self.poll_hz} must be in (0, 5]")
        if self.feed_deg_min <= 0:
            raise BadInputError(f"TurntableConfig.feed_deg_min={self.feed_deg_min} must be positive")
        if self.tilt_axis not in ("Y", "A"):
            raise BadInputError(f"TurntableConfig.tilt_axis={self.tilt_axis!r} must be 'Y' or 'A'")
        if not self.x_range_deg[1] - self.x_range_deg[0] >= 360.0:
            raise BadInputError(f"TurntableConfig.x_range_deg={self.x_range_deg} must span at least one turn")
