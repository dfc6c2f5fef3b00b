"""Move planning without I/O: the wrapped turntable target, soft-limit checks, and time allowances.

GRBL 1.1 has no rotary axis: X is a linear axis in degrees whose counter never wraps, and soft
limits ($20, $130/$131) bound the machine position to [-$13x, 0]. So the driver picks, among the
equivalent angles a+360k, one that keeps X inside a bounded window, and checks the machine target
against the travel before a line goes out. Time allowances follow GRBL's planner: the programmed
feed is the vector speed of the combined move, each axis capped by its own $11x rate and $12x
acceleration, the feed scaled by the `Ov` feed override.
"""

from __future__ import annotations

import math
from typing import Literal

from station.errors import BadInputError
from station.turntable.errors import SoftLimitError

Rotation = Literal["shortest", "continuous"]


def trapezoid_seconds(distance: float, rate_per_min: float, accel: float) -> float:
    """Rest-to-rest move time at `rate_per_min` with `accel` (units/s^2): GRBL's block profile."""
    v = rate_per_min / 60.0
    if distance * accel < v * v:
        return 2.0 * math.sqrt(distance / accel)
    return v / accel + distance / v


def move_seconds(delta: tuple[float, ...], feed_per_min: float, rates: tuple[float, ...],
                 accels: tuple[float, ...], feed_override_pct: float = 100.0) -> float:
    """Duration of one G1 move by `delta`: vector feed (scaled by the override) capped per axis."""
    length = math.sqrt(sum(d * d for d in delta))
    if length == 0.0:
        return 0.0
    speed = feed_per_min * feed_override_pct / 100.0
    accel = math.inf
    for d, rate, acc in zip(delta, rates, accels):
        share = abs(d) / length
        if share > 1e-12:
            speed = min(speed, rate / share)
            accel = min(accel, acc / share)
    return trapezoid_seconds(length, speed, accel)


def wrapped_target(angle_deg: float, current: float, rotation: Rotation, window: tuple[float, float]) -> float:
    """Work X for `angle_deg`: the least turn (or the next forward one), then wrapped into `window`.

    continuous: never decreasing, except the one 360 degree unwind when X would leave the window.
    """
    if not math.isfinite(angle_deg):
        raise BadInputError(f"turntable angle {angle_deg!r} is not a finite number")
    if rotation == "continuous":
        target = current + (angle_deg - current) % 360.0
    elif rotation == "shortest":
        target = current + ((angle_deg - current + 180.0) % 360.0 - 180.0)
    else:
        raise BadInputError(f"rotation mode {rotation!r} must be 'shortest' or 'continuous'")
    low, high = window
    while target > high:
        target -= 360.0
    while target < low:
        target += 360.0
    if target > high:
        raise SoftLimitError(f"turntable angle {angle_deg:g} has no equivalent inside the travel window "
                             f"[{low:g}, {high:g}] degrees (work coordinates)")
    return target


def x_window(configured: tuple[float, float], settings: dict[int, float], wco_x: float) -> tuple[float, float]:
    """The configured work window, narrowed to the soft-limit travel [-$130, 0] when $20=1."""
    low, high = configured
    if settings.get(20):
        low, high = max(low, -settings.get(130, 0.0) - wco_x), min(high, -wco_x)
    if high - low < 360.0:
        raise SoftLimitError(f"the turntable's travel window [{low:g}, {high:g}] degrees is narrower than one turn; "
                             f"widen $130 or TurntableConfig.x_range_deg")
    return low, high


def check_travel(axis_name: str, machine_target: float, settings: dict[int, float], axis: int) -> None:
    """Refuse a target GRBL would stop with ALARM:2 (soft limits on: machine travel is [-$13x, 0])."""
    if not settings.get(20):
        return
    travel = settings.get(130 + axis, 0.0)
    if not -travel - 1e-6 <= machine_target <= 1e-6:
        raise SoftLimitError(f"{axis_name} target {machine_target:g} (machine) is outside the soft-limit travel "
                             f"[{-travel:g}, 0] set by $20=1 and ${130 + axis}={travel:g}")
