"""Motion profiles for the GRBL emulator: trapezoids from rest to rest, and feed-hold decelerations.

Times here are firmware seconds; the emulator divides wall-clock time by its `time_scale` before
asking. Each block starts and ends at rest (no junction blending): a turntable driver sends one
move at a time, so real GRBL plans it the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Vec = tuple[float, ...]


@dataclass
class PlannerBlock:
    """One queued planner entry; it stays at the queue head while it runs (a feed hold resumes it)."""

    kind: Literal["move", "jog", "dwell", "home"]
    target: Vec  # machine coordinates
    feed: float | None = None  # units/min; None = rapid
    seconds: float = 0.0  # dwell length


@dataclass(frozen=True)
class Segment:
    """Straight motion from `start` along unit vector `direction`, `length` units long.

    kind: "move" (trapezoid from rest), "decel" (from speed `v0` down to rest), "dwell" or "home"
    (no profile: linear in time over `duration`).
    """

    kind: str
    t0: float  # wall-clock start
    start: Vec
    direction: Vec
    length: float
    duration: float  # firmware seconds
    accel: float = 0.0  # units/s^2
    v_peak: float = 0.0  # units/s (move: cruise speed reached; decel: starting speed)

    def end(self) -> Vec:
        return tuple(s + d * self.length for s, d in zip(self.start, self.direction))

    def distance(self, tau: float) -> float:
        """Distance travelled `tau` firmware seconds after the start."""
        tau = min(max(tau, 0.0), self.duration)
        if self.kind == "decel":
            return self.v_peak * tau - 0.5 * self.accel * tau * tau
        if self.kind != "move":
            return self.length * tau / self.duration if self.duration > 0 else self.length
        t_acc = self.v_peak / self.accel
        if tau <= t_acc:
            return 0.5 * self.accel * tau * tau
        if tau >= self.duration - t_acc:
            rest = self.duration - tau
            return self.length - 0.5 * self.accel * rest * rest
        return 0.5 * self.accel * t_acc * t_acc + self.v_peak * (tau - t_acc)

    def velocity(self, tau: float) -> float:
        """Speed (units/s) `tau` firmware seconds after the start."""
        if tau <= 0.0 or tau >= self.duration:
            return 0.0
        if self.kind == "decel":
            return self.v_peak - self.accel * tau
        if self.kind != "move":
            return self.length / self.duration
        return min(self.v_peak, self.accel * tau, self.accel * (self.duration - tau))

    def position(self, tau: float) -> Vec:
        s = self.distance(tau)
        return tuple(p + d * s for p, d in zip(self.start, self.direction))


def move_segment(t0: float, start: Vec, target: Vec, rate_limits: Vec, accel_limits: Vec, feed: float | None) -> Segment:
    """Trapezoid for a linear move. Rates are units/min, accelerations units/s^2, feed None = rapid.

    As in GRBL's planner, the move's speed and acceleration are the largest that keep every axis
    within its own `$11x` rate and `$12x` acceleration, and within the programmed feed.
    """
    delta = [t - s for s, t in zip(start, target)]
    length = math.sqrt(sum(d * d for d in delta))
    if length == 0.0:
        return Segment("move", t0, start, tuple(0.0 for _ in start), 0.0, 0.0, 1.0, 0.0)
    direction = tuple(d / length for d in delta)
    v_max = math.inf if feed is None else feed / 60.0
    accel = math.inf
    for u, rate, acc in zip(direction, rate_limits, accel_limits):
        if abs(u) > 1e-12:
            v_max = min(v_max, rate / 60.0 / abs(u))
            accel = min(accel, acc / abs(u))
    if length * accel < v_max * v_max:  # triangle: never reaches cruise speed
        v_max = math.sqrt(length * accel)
        duration = 2.0 * v_max / accel
    else:
        duration = v_max / accel + length / v_max
    return Segment("move", t0, start, direction, length, duration, accel, v_max)


def decel_segment(t0: float, start: Vec, direction: Vec, speed: float, accel: float) -> Segment:
    """Feed hold: brake from `speed` to rest along the current direction."""
    if speed <= 0.0:
        return Segment("decel", t0, start, direction, 0.0, 0.0, max(accel, 1e-9), 0.0)
    return Segment("decel", t0, start, direction, speed * speed / (2.0 * accel), speed / accel, accel, speed)


def timed_segment(kind: str, t0: float, start: Vec, target: Vec, duration: float) -> Segment:
    """Dwell or homing: covers `start`->`target` linearly in `duration` firmware seconds."""
    delta = [t - s for s, t in zip(start, target)]
    length = math.sqrt(sum(d * d for d in delta))
    direction = tuple(d / length for d in delta) if length > 0 else tuple(0.0 for _ in start)
    return Segment(kind, t0, start, direction, length, duration)
