"""GRBL 1.1 / grblHAL turntable driver: X is the turntable in degrees, Y (or A) the tilt arm.

The driver knows the wire protocol and nothing else (retries, resume and the manifest belong to the
scan session). Actions return a MoveStatus that carries the device's exception to whoever waits.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from station.errors import BadInputError, DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from station.turntable.errors import GrblSettingsError, TiltLimitError, UnexpectedResetError, WaitTimeoutError
from station.turntable.link import SerialLine
from station.turntable.protocol import FirmwareInfo, GrblProtocol
from station.turntable.recovery import Recovery, recover
from station.turntable.status import MachineStatus

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


class MoveStatus:
    """Completion of one action (ophyd style): `wait()` returns the result or re-raises the failure."""

    def __init__(self, description: str) -> None:
        self.description = description
        self._done = threading.Event()
        self._result: tuple[float, float] | None = None
        self._error: BaseException | None = None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def success(self) -> bool:
        return self._done.is_set() and self._error is None

    @property
    def exception(self) -> BaseException | None:
        return self._error

    def _finish(self, result: tuple[float, float] | None, error: BaseException | None) -> None:
        self._result, self._error = result, error
        self._done.set()

    def wait(self, timeout: float | None = None) -> tuple[float, float]:
        """Position reached (turntable, tilt) in degrees; WaitTimeoutError if *we* stopped waiting."""
        if not self._done.wait(timeout):
            raise WaitTimeoutError(f"stopped waiting after {timeout} s for {self.description}; it is still running")
        if self._error is not None:
            raise self._error
        return self._result  # type: ignore[return-value]  # set together with _done when no error


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

    # ---- connection ---------------------------------------------------------------------
    @classmethod
    def connect(cls, port: str, config: TurntableConfig | None = None, *, timeout: float | None = None) -> Turntable:
        """Open `port` (device path or pyserial URL), reset, identify, check settings, get ready.

        A board found in Alarm is re-homed when homing is enabled ($22=1), else unlocked with $X (a
        soft reset keeps GRBL's step counter, so its position stands).
        """
        config = config or TurntableConfig()
        if timeout is not None:
            config = TurntableConfig(**{**config.__dict__, "banner_timeout_s": timeout})
        table = cls(port, config)
        with table._io:
            table._open()
            table._establish()
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
        """Work position now: (turntable unwrapped, tilt) degrees."""
        return self._work(self.status())

    def _guard(self, action: Callable[[], object], *, moving: bool = False):  # type: ignore[no-untyped-def]
        """Run an I/O action; remember when the board's step counter can no longer be trusted."""
        try:
            return action()
        except DeviceDisconnectedError:
            self._lose_counter(moving)
            if self._proto is not None:
                self._proto.line.close()
                self._proto = None
            raise
        except UnexpectedResetError:
            self._lose_counter(moving)
            raise

    def _lose_counter(self, moving: bool) -> None:
        self._counter_lost = True
        self._counter_lost_mid_move = self._counter_lost_mid_move or moving

    # ---- actions ----------------------------------------------------------------------------
    def _spawn(self, description: str, work: Callable[[], tuple[float, float]]) -> MoveStatus:
        status = MoveStatus(description)

        def run() -> None:
            try:
                with self._io:
                    result = self._guard(work, moving=True)
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
        """Absolute move (G90 G1) to turntable angle and tilt, both in degrees."""
        low, high = self.config.tilt_limits_deg
        if not (math.isfinite(tilt_deg) and low <= tilt_deg <= high):
            raise TiltLimitError(f"tilt {tilt_deg!r} degrees is outside the limits [{low:g}, {high:g}]")
        target = (self.target_for(angle_deg, rotation), float(tilt_deg))
        return self._spawn(f"move to {target[0]:.3f}, {target[1]:.3f} deg", lambda: self._move_locked(target))

    def home(self) -> MoveStatus:
        """Homing cycle ($H); GRBL answers ok only once homing is complete."""
        return self._spawn("homing", self._home_locked)

    def unlock(self) -> None:
        """Clear an alarm lock without homing ($X)."""
        with self._io:
            self._guard(lambda: self._p.command("$X", self.config.reply_timeout_s))

    def feed_hold(self) -> None:
        """Decelerate to a stop (`!`), keeping position; a running move waits through the hold."""
        self._p.line.write(b"!")

    def resume(self, timeout: float | None = None) -> None:
        """Cycle start (`~`), sent only once the hold is complete (Hold:0): GRBL ignores it in Hold:1."""
        deadline = time.monotonic() + (timeout or self.config.reply_timeout_s + self.config.motion_margin_s)
        self._wait_state(lambda s: s.state in ("Hold", "Door") and s.substate == 0, deadline, "Hold:0")
        self._p.line.write(b"~")

    def _wait_state(self, ok: Callable[[MachineStatus], bool], deadline: float, what: str) -> None:
        period = 1.0 / self.config.poll_hz
        while time.monotonic() < deadline:
            if self._io.acquire(blocking=False):  # nobody is polling for us: poll ourselves
                try:
                    if ok(self._guard(lambda: self._p.query_status(self.config.reply_timeout_s))):
                        return
                finally:
                    self._io.release()
                time.sleep(period)
            else:  # a running move polls; watch its reports
                with self._status_cond:
                    seen = self._last_status
                    if seen is not None and ok(seen):
                        return
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
        proto.line.write(line.encode("ascii") + b"\n")
        if proto.await_reply(line, time.monotonic() + cfg.reply_timeout_s) is None:
            # A dropped `ok`: the line was taken if the table is moving or already there.
            status = proto.query_status(cfg.reply_timeout_s)
            if not (status.state in ("Run", "Hold") or self._at(status, target)):
                raise DeviceTimeoutError(f"turntable on {self.port} never answered {line!r} and is "
                                         f"{status.state} at {self._work(status)}, not moving to {target}")
        proto.line.write(b"G4 P0\n")

        def hold_extends(status: MachineStatus) -> float | None:
            return time.monotonic() + budget if status.state in ("Hold", "Door") else None

        reply = proto.await_reply("G4 P0", time.monotonic() + budget, poll_s=1.0 / cfg.poll_hz, extend=hold_extends)
        status = proto.query_status(cfg.reply_timeout_s)
        if not (status.state == "Idle" and self._at(status, target)):
            waited = "no ok to G4 P0" if reply is None else "G4 P0 answered"
            raise DeviceTimeoutError(f"turntable on {self.port}: {waited} after {budget:.1f} s, table is "
                                     f"{status.state} at {self._work(status)}, target {target}")
        self._known = self._work(status)
        return self._known

    def recover(self) -> Recovery:
        """Bring the table back after a vanished port, a board reset, or an alarm; see `recovery.recover`."""
        return recover(self)

    def _home_locked(self) -> tuple[float, float]:
        self._p.command("$H", self.config.home_timeout_s)
        self._read_wco()
        self._known = self._work(self._p.query_status(self.config.reply_timeout_s))
        return self._known
