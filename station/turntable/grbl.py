"""GRBL 1.1 / grblHAL turntable driver: X is the turntable in degrees, Y (or A) the tilt arm.

The driver knows the wire protocol and nothing else (retries, resume and the manifest belong to the
scan session). Actions return a MoveStatus that carries the device's exception to whoever waits.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal, TypeVar

from station.errors import BadInputError, DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from station.turntable.action import MoveStatus
from station.turntable.errors import GrblSettingsError, MoveCancelledError, TiltLimitError, UnexpectedResetError
from station.turntable.link import SerialLine
from station.turntable.protocol import FirmwareInfo, GrblProtocol
from station.turntable.recovery import Recovery, recover
from station.turntable.status import MachineStatus

T = TypeVar("T")
Rotation = Literal["shortest", "continuous"]
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2, "A": 3}


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
    baudrate: int = 115200
    banner_timeout_s: float = 3.0
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


def trapezoid_seconds(distance: float, rate_per_min: float, accel: float) -> float:
    """Rest-to-rest move time at `rate_per_min` with `accel` (units/s^2): GRBL's block profile."""
    v = rate_per_min / 60.0
    if distance * accel < v * v:
        return 2.0 * math.sqrt(distance / accel)
    return v / accel + distance / v


class Turntable:
    """A connected turntable. Build with `Turntable.connect(port)`; one action at a time."""

    def __init__(self, port: str, config: TurntableConfig) -> None:
        self.port = port
        self.config = config
        self.info: FirmwareInfo | None = None
        self._axis = _AXIS_INDEX[config.tilt_axis]
        self._io = threading.RLock()  # held by whoever reads replies
        self._proto: GrblProtocol | None = None
        self._wco: tuple[float, ...] | None = None
        self._known = (0.0, 0.0)  # last confirmed work position (turntable unwrapped, tilt)
        self._last_seen = (0.0, 0.0)  # freshest position from any status report
        self._status_cond = threading.Condition()
        self._last_status: MachineStatus | None = None
        self._counter_lost = False  # the board rebooted or the link dropped: its MPos can't be trusted
        self._counter_lost_mid_move = False
        self._in_motion = False  # a motion line went out and has not been seen complete
        self._cancelling = threading.Event()

    # ---- connection ---------------------------------------------------------------------
    @classmethod
    def connect(cls, port: str, config: TurntableConfig | None = None, *, timeout: float | None = None) -> Turntable:
        """Open `port` (device path or pyserial URL), reset, identify, check settings, get ready.

        A board found in Alarm is re-homed when homing is enabled ($22=1), else unlocked with $X (a
        soft reset keeps GRBL's step counter, so its position stands).
        """
        config = config or TurntableConfig()
        if timeout is not None:
            config = replace(config, banner_timeout_s=timeout)
        table = cls(port, config)
        with table._io:
            table._open()
            try:
                table._establish()
            except BaseException:
                table.close()  # a refused port must not stay open (a retry or another program needs it)
                raise
        return table

    def _open(self) -> None:
        self._proto = GrblProtocol(SerialLine(self.port, self.config.baudrate), self._note_status)

    def _identify(self) -> MachineStatus:
        """Reset, banner, `$I`, `$$` check and `$#` offsets; returns the first status report."""
        proto = self._p
        flavour, version = proto.handshake(self.config.banner_timeout_s)
        self.info = proto.identify(flavour, version, self.config.reply_timeout_s)
        self._check_settings(self.info.settings)
        self._read_wco()
        return proto.query_status(self.config.reply_timeout_s)

    def _establish(self) -> None:
        proto = self._p
        status = self._identify()
        if status.state == "Alarm":
            if self.homing_enabled:
                self._home_locked()
            else:
                proto.command("$X", self.config.reply_timeout_s)
        self._known = self._last_seen = self._work(proto.query_status(self.config.reply_timeout_s))

    @property
    def _p(self) -> GrblProtocol:
        if self._proto is None:
            raise DeviceDisconnectedError(f"turntable on {self.port} is not connected; call recover()")
        return self._proto

    @property
    def homing_enabled(self) -> bool:
        return bool(self.info and self.info.settings.get(22, 0))

    def close(self) -> None:
        with self._io:
            if self._proto is not None:
                self._proto.line.close()
                self._proto = None

    def __enter__(self) -> Turntable:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_settings(self, settings: dict[int, float]) -> None:
        cfg = self.config
        expected: dict[int, tuple[float, str]] = {}
        for j, axis in enumerate((0, self._axis)):
            expected[100 + axis] = (cfg.steps_per_deg[j], "steps/degree")
            expected[110 + axis] = (cfg.max_rate_deg_min[j], "degree/min max rate")
            expected[120 + axis] = (cfg.accel_deg_s2[j], "degree/s^2 acceleration")
        wrong = []
        for number, (want, unit) in expected.items():
            have = settings.get(number)
            if have is None:
                wrong.append(f"${number} missing (expected {want:g} {unit})")
            elif abs(have - want) > cfg.settings_rel_tol * abs(want):
                wrong.append(f"${number}={have:g} (expected {want:g} {unit})")
        if wrong:
            raise GrblSettingsError(f"turntable on {self.port} is configured differently from the rig: " + ", ".join(wrong))

    def _read_wco(self) -> None:
        info = self._p.command("$#", self.config.reply_timeout_s)
        offsets = {s[1:].split(":")[0]: s[1:-1].split(":")[1] for s in info if s.count(":") >= 1}
        try:
            g54 = [float(v) for v in offsets["G54"].split(",")]
            g92 = [float(v) for v in offsets["G92"].split(",")]
        except (KeyError, ValueError) as exc:
            raise DeviceError(f"turntable on {self.port} sent unreadable $# offsets {info!r}") from exc
        self._wco = tuple(a + b for a, b in zip(g54, g92))

    # ---- status -----------------------------------------------------------------------------
    def _note_status(self, status: MachineStatus) -> None:
        if status.wco is not None:
            self._wco = status.wco
        work = status.work_position(self._wco)
        if work is not None:
            self._last_seen = (work[0], work[self._axis])
        with self._status_cond:
            self._last_status = status
            self._status_cond.notify_all()

    def _work(self, status: MachineStatus) -> tuple[float, float]:
        work = status.work_position(self._wco)
        if work is None:
            raise DeviceError(f"turntable on {self.port} reported no usable position: {status}")
        return (work[0], work[self._axis])

    def status(self) -> MachineStatus:
        """A fresh `?` report (a garbled one is refused and asked again once)."""
        with self._io:
            return self._guard(lambda: self._p.query_status(self.config.reply_timeout_s))

    def position(self) -> tuple[float, float]:
        """Work position now: (turntable unwrapped, tilt) degrees; waits for a running action."""
        return self._work(self.status())

    def _guard(self, action: Callable[[], T]) -> T:
        """Run an I/O action; remember when the board's step counter can no longer be trusted."""
        self._in_motion = False  # the action sets it once a motion line has gone out
        try:
            return action()
        except DeviceDisconnectedError:
            self._lose_counter()
            if self._proto is not None:
                self._proto.line.close()
                self._proto = None
            raise
        except UnexpectedResetError:
            self._lose_counter()
            raise

    def _lose_counter(self) -> None:
        self._counter_lost = True
        self._counter_lost_mid_move = self._counter_lost_mid_move or self._in_motion

    # ---- actions ----------------------------------------------------------------------------
    def _spawn(self, description: str, work: Callable[[], tuple[float, float]]) -> MoveStatus:
        status = MoveStatus(description)

        def run() -> None:
            try:
                with self._io:
                    result = self._guard(work)
            except BaseException as exc:  # handed to whoever waits, as ophyd's status does
                status._finish(None, exc)
            else:
                status._finish(result, None)

        threading.Thread(target=run, name=f"turntable {description}", daemon=True).start()
        return status

    def target_for(self, angle_deg: float, rotation: Rotation | None = None) -> float:
        """Unwrapped turntable coordinate for `angle_deg` from where the table is now.

        continuous: always forward (never decreasing); shortest: the least rotation, either way.
        """
        if not math.isfinite(angle_deg):
            raise BadInputError(f"turntable angle {angle_deg!r} is not a finite number")
        current = self._known[0]
        mode = rotation or self.config.rotation
        if mode == "continuous":
            return current + (angle_deg - current) % 360.0
        if mode == "shortest":
            return current + ((angle_deg - current + 180.0) % 360.0 - 180.0)
        raise BadInputError(f"rotation mode {mode!r} must be 'shortest' or 'continuous'")

    def move_to(self, angle_deg: float, tilt_deg: float, rotation: Rotation | None = None) -> MoveStatus:
        """Absolute move (G90 G1) to turntable angle and tilt, both in degrees.

        Bad input raises here; everything the device does is reported through the returned status.
        The unwrapped target is taken from where the previous action left the table.
        """
        low, high = self.config.tilt_limits_deg
        if not (math.isfinite(tilt_deg) and low <= tilt_deg <= high):
            raise TiltLimitError(f"tilt {tilt_deg!r} degrees is outside the limits [{low:g}, {high:g}]")
        self.target_for(angle_deg, rotation)  # validates angle and mode now, not in the worker

        def move() -> tuple[float, float]:
            return self._move_locked((self.target_for(angle_deg, rotation), float(tilt_deg)))

        return self._spawn(f"move to {angle_deg:g} deg, tilt {tilt_deg:g} deg", move)

    def home(self) -> MoveStatus:
        """Homing cycle ($H); GRBL answers ok only once homing is complete."""
        return self._spawn("homing", self._home_locked)

    def unlock(self) -> None:
        """Clear an alarm lock without homing ($X)."""
        with self._io:
            self._guard(lambda: self._p.command("$X", self.config.reply_timeout_s))

    def feed_hold(self) -> None:
        """Decelerate to a stop (`!`), keeping position; a running move waits through the hold."""
        with self._status_cond:
            self._last_status = None  # resume() must see a report from after this hold
        self._p.line.write(b"!")

    def cancel(self, timeout: float | None = None) -> None:
        """Operator stop of the running move: hold, wait for Hold:0, then soft-reset.

        GRBL keeps its position when reset from a completed hold (no ALARM:3), so the running move
        ends in MoveCancelledError with the work position restored, distinct from any device fault.
        Does nothing when no move is running.
        """
        if self._io.acquire(blocking=False):
            self._io.release()
            return
        self._cancelling.set()
        self.feed_hold()
        deadline = time.monotonic() + (timeout or self.config.reply_timeout_s + self.config.motion_margin_s)
        seen = self._wait_state(lambda s: s.state == "Idle" or (s.state == "Hold" and s.substate == 0), deadline, "Hold:0")
        if seen.state == "Hold":
            self._p.line.write(b"\x18")
        else:
            self._cancelling.clear()  # it finished before the hold took

    def resume(self, timeout: float | None = None) -> None:
        """Cycle start (`~`), sent only once the hold is complete (Hold:0): GRBL ignores it in Hold:1."""
        deadline = time.monotonic() + (timeout or self.config.reply_timeout_s + self.config.motion_margin_s)
        self._wait_state(lambda s: s.state in ("Hold", "Door") and s.substate == 0, deadline, "Hold:0")
        self._p.line.write(b"~")

    def _wait_state(self, ok: Callable[[MachineStatus], bool], deadline: float, what: str) -> MachineStatus:
        period = 1.0 / self.config.poll_hz
        while time.monotonic() < deadline:
            if self._io.acquire(blocking=False):  # nobody is polling for us: poll ourselves
                try:
                    status = self._guard(lambda: self._p.query_status(self.config.reply_timeout_s))
                    if ok(status):
                        return status
                finally:
                    self._io.release()
                time.sleep(period)
            else:  # a running move polls; watch its reports
                with self._status_cond:
                    seen = self._last_status
                    if seen is not None and ok(seen):
                        return seen
                    self._status_cond.wait(min(period, max(0.0, deadline - time.monotonic())))
        raise DeviceTimeoutError(f"turntable on {self.port} did not reach {what} in time")

    # ---- blocking bodies (called with self._io held) ---------------------------------------
    def _estimate_s(self, target: tuple[float, float]) -> float:
        settings = self.info.settings if self.info else {}
        seconds = 0.0
        for j, axis in enumerate((0, self._axis)):
            rate = min(self.config.feed_deg_min, settings.get(110 + axis, self.config.max_rate_deg_min[j]))
            accel = settings.get(120 + axis, self.config.accel_deg_s2[j])
            seconds = max(seconds, trapezoid_seconds(abs(target[j] - self._last_seen[j]), rate, accel))
        return seconds

    def _at(self, status: MachineStatus, target: tuple[float, float]) -> bool:
        work = self._work(status)
        steps = self.info.settings if self.info else {}
        tolerance = [1.5 / steps.get(100 + axis, 1000.0) + 1e-6 for axis in (0, self._axis)]
        return all(abs(w - t) <= tol for w, t, tol in zip(work, target, tolerance))

    def _move_locked(self, target: tuple[float, float]) -> tuple[float, float]:
        proto, cfg = self._p, self.config
        line = f"G90 G1 X{target[0]:.4f} {cfg.tilt_axis}{target[1]:.4f} F{cfg.feed_deg_min:.1f}"
        budget = self._estimate_s(target) * 1.5 + cfg.motion_margin_s
        proto.drain()  # a board that rebooted while idle must not take this line in its new frame
        proto.line.write(line.encode("ascii") + b"\n")
        self._in_motion = True
        if proto.await_reply(line, time.monotonic() + cfg.reply_timeout_s) is None:
            # A dropped `ok`: the line was taken if the table is moving or already there.
            status = proto.query_status(cfg.reply_timeout_s)
            if not (status.state in ("Run", "Hold") or self._at(status, target)):
                raise DeviceTimeoutError(f"turntable on {self.port} never answered {line!r} and is "
                                         f"{status.state} at {self._work(status)}, not moving to {target}")
        proto.line.write(b"G4 P0\n")

        def adjust(status: MachineStatus, deadline: float) -> float:
            if status.state in ("Hold", "Door"):
                return max(deadline, time.monotonic() + budget)
            if status.state == "Idle" and self._at(status, target):
                return min(deadline, time.monotonic() + cfg.reply_timeout_s)
            return deadline

        try:
            reply = proto.await_reply("G4 P0", time.monotonic() + budget, poll_s=1.0 / cfg.poll_hz, adjust=adjust)
        except UnexpectedResetError:
            if not self._cancelling.is_set():
                raise
            self._cancelling.clear()
            raise MoveCancelledError(f"move to {target} cancelled by the operator; "
                                     f"table stopped at {self._restore_after_reset()}") from None
        status = proto.query_status(cfg.reply_timeout_s)
        if not (status.state == "Idle" and self._at(status, target)):
            waited = "no ok to G4 P0" if reply is None else "G4 P0 answered"
            raise DeviceTimeoutError(f"turntable on {self.port}: {waited} after {budget:.1f} s, table is "
                                     f"{status.state} at {self._work(status)}, target {target}")
        self._known = self._work(status)
        return self._known

    def _restore_after_reset(self) -> tuple[float, float]:
        """A reset from rest keeps MPos but clears G92: put the old work offset back."""
        old_wco = self._wco or (0.0,) * (self._axis + 1)
        mpos = self._p.query_status(self.config.reply_timeout_s).machine_position(self._wco)
        work = (mpos[0] - old_wco[0], mpos[self._axis] - old_wco[self._axis])
        self._p.command(f"G92 X{work[0]:.4f} {self.config.tilt_axis}{work[1]:.4f}", self.config.reply_timeout_s)
        self._read_wco()
        self._known = self._last_seen = self._work(self._p.query_status(self.config.reply_timeout_s))
        return self._known

    def recover(self) -> Recovery:
        """Bring the table back after a vanished port, a board reset, or an alarm; see `recovery.recover`."""
        return recover(self)

    def _home_locked(self) -> tuple[float, float]:
        self._p.drain()
        self._in_motion = True
        self._p.command("$H", self.config.home_timeout_s)
        self._read_wco()
        self._known = self._work(self._p.query_status(self.config.reply_timeout_s))
        return self._known
