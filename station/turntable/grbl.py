"""GRBL 1.1 / grblHAL turntable driver: X is the turntable in degrees, Y (or A) the tilt arm.

The driver knows the wire protocol and nothing else (retries, resume and the manifest belong to the
scan session). Actions return a MoveStatus that carries the device's exception to whoever waits.
The position reference is the G54 work offset, set with G10 L20 P1 and never with G92.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Literal, TypeVar

from station.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from station.turntable.action import MoveStatus
from station.turntable.config import TurntableConfig
from station.turntable.errors import GrblAlarm, MoveCancelledError, TiltLimitError, UnexpectedResetError
from station.turntable.link import SerialLine
from station.turntable.planning import Rotation, check_travel, move_seconds, wrapped_target, x_window
from station.turntable.protocol import FirmwareInfo, GrblProtocol
from station.turntable.recovery import Recovery, TurntableRecovery
from station.turntable.reference import Reference, read_reference
from station.turntable.reset import check_settings, check_startup_echoes, hold_until_still, set_modal_state
from station.turntable.status import MachineStatus

log = logging.getLogger(__name__)
T = TypeVar("T")
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2, "A": 3}
CounterLoss = Literal["none", "at_rest", "mid_move"]
SUDDEN_HALT_ALARMS = (1, 3)  # hard limit, reset while moving: GRBL says the position is likely lost


class Turntable:
    """A connected turntable. Build with `Turntable.connect(port)`; one action at a time."""

    def __init__(self, port: str, config: TurntableConfig) -> None:
        self.port = port
        self.config = config
        self.info: FirmwareInfo | None = None
        self.position_exact = True  # False once a reset caught the table moving (ALARM:3) or a reboot cut a move
        self._axis = _AXIS_INDEX[config.tilt_axis]
        self._io = threading.RLock()  # held by whoever reads replies
        self._proto: GrblProtocol | None = None
        self._reference: Reference | None = None
        self._wco: tuple[float, ...] | None = None
        self._known = (0.0, 0.0)  # last confirmed work position (turntable, tilt)
        self._last_seen = (0.0, 0.0)  # freshest work position from any status report
        self._rest_mpos: tuple[float, ...] | None = None  # machine position where the last action left it
        self._flight: tuple[tuple[float, ...], tuple[float, ...]] | None = None  # machine start, target of a move
        self._override = 100.0  # feed override (Ov) last reported
        self._status_cond = threading.Condition()
        self._last_status: MachineStatus | None = None
        self._loss: CounterLoss = "none"
        self._cancelling = threading.Event()

    # ---- connection ---------------------------------------------------------------------
    @classmethod
    def connect(cls, port: str, config: TurntableConfig | None = None, *, timeout: float | None = None) -> Turntable:
        """Open `port` (device path or pyserial URL), stop any motion, reset, identify, check, get ready.

        A board found in Alarm is re-homed when homing is enabled ($22=1), else unlocked with $X (a
        soft reset from rest keeps GRBL's step counter, so its position stands).
        """
        config = config or TurntableConfig()
        if timeout is not None:
            config = replace(config, banner_timeout_s=timeout)
        table = cls(port, config)
        with table._io:
            try:
                table.reconnect()
                if table.status().state == "Alarm":
                    if table.homing_enabled:
                        table.rehome()
                    else:
                        table.unlock()
                table._settle(table.status())
            except BaseException:
                table.close()  # a refused port must not stay open (a retry or another program needs it)
                raise
        return table

    def reconnect(self) -> None:
        """Reopen the port if needed, hold a moving table, reset, identify, set modal state, check the reference.

        Afterwards the step counter is compared with where the driver last saw it: a board that
        rebooted (counter restarted at zero) is marked so that `counter_loss` says so.
        """
        with self._io:
            if self._proto is None:
                self._proto = GrblProtocol(SerialLine(self.port, self.config.baudrate), self._note_status)
            self._guard(self._establish)

    def _establish(self) -> None:
        proto, cfg = self._p, self.config
        hold_until_still(proto, proto.probe(min(0.5, cfg.reply_timeout_s)), cfg)
        shake = proto.handshake(cfg.banner_timeout_s, cfg.banner_retry_s)
        if set(shake.alarms) & set(SUDDEN_HALT_ALARMS):
            self._mark_inexact(f"the reset reported {', '.join(f'ALARM:{a}' for a in shake.alarms)}")
        self.info = proto.identify(shake.flavour, shake.version, cfg.reply_timeout_s)
        check_settings(self.info.settings, cfg, self._axis, self.port)
        check_startup_echoes(shake.startup, self.port)
        if proto.query_status(cfg.reply_timeout_s).state != "Alarm":  # G-code is locked in Alarm: after $X/$H
            set_modal_state(proto, cfg.reply_timeout_s)
        self._check_counter(self._read_reference())

    def _read_reference(self) -> MachineStatus:
        """`$#` offsets, then a status report checked against them; returns that report."""
        self._reference = read_reference(self._p, self.config.reply_timeout_s)
        self._wco = self._reference.wco
        status = self._p.query_status(self.config.reply_timeout_s)
        self._reference.check(status, self.port)
        return status

    def _check_counter(self, status: MachineStatus) -> None:
        """A rebooted board restarts MPos at zero: its counter no longer matches where the table is."""
        mpos = status.machine_position(self._wco)
        if mpos is None:
            return
        if self._rest_mpos is None:  # first connect: nothing seen before, but a fresh count is telling
            if all(m == 0.0 for m in mpos) and self._reference and any(abs(g) > 1e-3 for g in self._reference.g54):
                self._mark_inexact("it reports MPos 0 with a stored G54 reference, as after a power-up: "
                                   "if the table was moved or the board restarted since, angles are off")
            return
        tol = self._tolerances()
        here = (mpos[0], mpos[self._axis])
        if self._flight is not None:
            start, end = self._flight
            inside = all(min(s, e) - t <= h <= max(s, e) + t for h, s, e, t in zip(here, start, end, tol))
            if not inside:
                self._loss = "mid_move"
        elif not all(abs(h - r) <= t for h, r, t in zip(here, self._rest_mpos, tol)):
            self._loss = "at_rest"

    @property
    def _p(self) -> GrblProtocol:
        if self._proto is None:
            raise DeviceDisconnectedError(f"turntable on {self.port} is not connected; call recover()")
        return self._proto

    @property
    def homing_enabled(self) -> bool:
        return bool(self.info and self.info.settings.get(22, 0))

    def settings(self) -> dict[int, float]:
        """The board's `$$` settings as read at the last connect."""
        return dict(self.info.settings) if self.info else {}

    @property
    def reference(self) -> Reference | None:
        """The stored G54 work offset and G92 offset as read (`$#`) at the last connect."""
        return self._reference

    def close(self) -> None:
        with self._io:
            if self._proto is not None:
                self._proto.line.close()
                self._proto = None

    def __enter__(self) -> Turntable:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the line: no action runs until the block ends (recovery works inside one)."""
        with self._io:
            yield

    # ---- status -----------------------------------------------------------------------------
    def _note_status(self, status: MachineStatus) -> None:
        if status.wco is not None:
            self._wco = status.wco
        if status.overrides:
            self._override = float(status.overrides[0])
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

    def _machine(self, work: tuple[float, float]) -> tuple[float, float]:
        wco = self._wco or (0.0,) * (self._axis + 1)
        return (work[0] + wco[0], work[1] + wco[self._axis])

    def _tolerances(self) -> tuple[float, float]:
        steps = self.info.settings if self.info else {}
        return tuple(1.5 / steps.get(100 + axis, 1000.0) + 1e-3 for axis in (0, self._axis))  # type: ignore[return-value]

    def status(self) -> MachineStatus:
        """A fresh `?` report (a garbled one is refused and asked again once)."""
        with self._io:
            return self._guard(lambda: self._p.query_status(self.config.reply_timeout_s))

    def position(self) -> tuple[float, float]:
        """Work position now: (turntable, tilt) degrees; waits for a running action."""
        return self._work(self.status())

    @property
    def last_seen(self) -> tuple[float, float]:
        """The freshest work position any status report gave, even one from before a fault."""
        return self._last_seen

    @property
    def counter_loss(self) -> CounterLoss:
        """Whether the board's step counter stopped matching the table: none, lost at rest, or mid-move."""
        return self._loss

    def _guard(self, action: Callable[[], T]) -> T:
        """Run an I/O action; remember when the board's step counter can no longer be trusted."""
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
        except GrblAlarm as alarm:
            if alarm.code in SUDDEN_HALT_ALARMS:
                self._mark_inexact(f"ALARM:{alarm.code} stopped it dead mid-move")
            raise

    def _lose_counter(self) -> None:
        if self._loss != "mid_move":
            self._loss = "mid_move" if self._flight is not None else "at_rest"

    def _mark_inexact(self, why: str) -> None:
        self.position_exact = False
        log.warning("turntable on %s: position is not exact: %s; re-home or re-reference before trusting angles",
                    self.port, why)

    def reference_to(self, work: tuple[float, float], *, exact: bool) -> tuple[float, float]:
        """Declare that the table stands at `work` now: G10 L20 P1 stores the G54 offset in EEPROM.

        Used after the step counter was lost; `exact` says whether `work` is known or only the last
        position seen. The counter is trusted again afterwards.
        """
        with self._io:
            proto, timeout = self._p, self.config.reply_timeout_s
            proto.command(f"G10 L20 P1 X{work[0]:.4f} {self.config.tilt_axis}{work[1]:.4f}", timeout)
            status = self._read_reference()
            here = self._work(status)
            if not all(abs(h - w) <= t for h, w, t in zip(here, work, self._tolerances())):
                raise DeviceError(f"turntable on {self.port}: after G10 L20 the work position is {here}, expected {work}")
            self._settle(status)
            self._loss = "none"
            if not exact:
                self._mark_inexact(f"restored to {work}, the last position seen before the board lost its count")
            return self._known

    def resync(self) -> tuple[float, float]:
        """Take the board's own position as where the table stands (its step counter was kept)."""
        with self._io:
            self._settle(self._guard(lambda: self._p.query_status(self.config.reply_timeout_s)))
            return self._known

    def _settle(self, status: MachineStatus) -> None:
        self._known = self._last_seen = self._work(status)
        mpos = status.machine_position(self._wco)
        self._rest_mpos = (mpos[0], mpos[self._axis]) if mpos else None
        self._flight = None

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
        """Work X for `angle_deg` from where the table is now, kept inside the travel window.

        continuous: forward (never decreasing) but for one unwind at the window's end; shortest: the
        least rotation either way. Leaving the window wraps by a whole turn: X never counts up forever.
        """
        window = self.config.x_range_deg
        if self.info is not None:
            window = x_window(window, self.info.settings, (self._wco or (0.0,))[0])
        return wrapped_target(angle_deg, self._known[0], rotation or self.config.rotation, window)

    def move_to(self, angle_deg: float, tilt_deg: float, rotation: Rotation | None = None) -> MoveStatus:
        """Absolute move (G90 G1) to turntable angle and tilt, both in degrees.

        Bad input (tilt limits, soft limits) raises here; everything the device does is reported
        through the returned status. The target is taken from where the previous action left the table.
        """
        low, high = self.config.tilt_limits_deg
        if not (math.isfinite(tilt_deg) and low <= tilt_deg <= high):
            raise TiltLimitError(f"tilt {tilt_deg!r} degrees is outside the limits [{low:g}, {high:g}]")
        self._check_travel((self.target_for(angle_deg, rotation), float(tilt_deg)))  # now, not in the worker

        def move() -> tuple[float, float]:
            target = (self.target_for(angle_deg, rotation), float(tilt_deg))
            self._check_travel(target)
            return self._move_locked(target)

        return self._spawn(f"move to {angle_deg:g} deg, tilt {tilt_deg:g} deg", move)

    def _check_travel(self, target: tuple[float, float]) -> None:
        settings = self.info.settings if self.info else {}
        machine = self._machine(target)
        check_travel("turntable X", machine[0], settings, 0)
        check_travel(f"tilt {self.config.tilt_axis}", machine[1], settings, self._axis)

    def home(self) -> MoveStatus:
        """Homing cycle ($H); GRBL answers ok only once homing is complete."""
        return self._spawn("homing", self.rehome)

    def unlock(self) -> None:
        """Clear an alarm lock without homing ($X)."""
        with self._io:
            self._guard(lambda: self._p.command("$X", self.config.reply_timeout_s))
            self._guard(lambda: set_modal_state(self._p, self.config.reply_timeout_s))

    def feed_hold(self) -> None:
        """Decelerate to a stop (`!`), keeping position; a running move waits through the hold."""
        with self._status_cond:
            self._last_status = None  # resume() must see a report from after this hold
        self._p.line.write(b"!")

    def cancel(self, timeout: float | None = None) -> None:
        """Operator stop of the running move: hold, wait for Hold:0, then soft-reset.

        GRBL keeps its position when reset from a completed hold (no ALARM:3), and the G54 reference
        lives in EEPROM, so the running move ends in MoveCancelledError with the position intact.
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
    def _estimate_s(self, start: tuple[float, float], target: tuple[float, float]) -> float:
        """Move time from `start` at the programmed vector feed, the axis limits and the feed override."""
        settings = self.info.settings if self.info else {}
        axes = (0, self._axis)
        rates = tuple(settings.get(110 + a, self.config.max_rate_deg_min[j]) for j, a in enumerate(axes))
        accels = tuple(settings.get(120 + a, self.config.accel_deg_s2[j]) for j, a in enumerate(axes))
        delta = (target[0] - start[0], target[1] - start[1])
        return move_seconds(delta, self.config.feed_deg_min, rates, accels, max(self._override, 1.0))

    def _at(self, status: MachineStatus, target: tuple[float, float]) -> bool:
        work = self._work(status)
        return all(abs(w - t) <= tol for w, t, tol in zip(work, target, self._tolerances()))

    def _move_locked(self, target: tuple[float, float]) -> tuple[float, float]:
        proto, cfg = self._p, self.config
        line = f"G90 G1 X{target[0]:.4f} {cfg.tilt_axis}{target[1]:.4f} F{cfg.feed_deg_min:.1f}"
        proto.drain()  # a board that rebooted while idle must not take this line in its new frame
        self._flight = (self._machine(self._known), self._machine(target))
        proto.line.write(line.encode("ascii") + b"\n")
        if proto.await_reply(line, time.monotonic() + cfg.reply_timeout_s) is None:
            # A dropped `ok`: the line was taken if the table is moving or already there.
            status = proto.query_status(cfg.reply_timeout_s)
            if not (status.state in ("Run", "Hold") or self._at(status, target)):
                raise DeviceTimeoutError(f"turntable on {self.port} never answered {line!r} and is "
                                         f"{status.state} at {self._work(status)}, not moving to {target}")
        proto.line.write(b"G4 P0\n")
        allowance = self._estimate_s(self._known, target) * 1.5 + cfg.motion_margin_s

        def adjust(status: MachineStatus, deadline: float) -> float:
            now = time.monotonic()
            if status.state in ("Hold", "Door"):
                return max(deadline, now + allowance)
            if status.state == "Run":  # what is left, at the feed override reported now
                return max(deadline, now + self._estimate_s(self._work(status), target) * 1.5 + cfg.motion_margin_s)
            if status.state == "Idle" and self._at(status, target):
                return min(deadline, now + cfg.reply_timeout_s)
            if status.state == "Idle" and not self._cancelling.is_set():
                self._restart_stalled_cycle(status, target)
            return deadline

        try:
            reply = proto.await_reply("G4 P0", time.monotonic() + allowance, poll_s=1.0 / cfg.poll_hz, adjust=adjust)
            status = proto.query_status(cfg.reply_timeout_s)  # a reset mid-move answers G4 P0, then ALARM:3
        except UnexpectedResetError:
            if not self._cancelling.is_set():
                raise
            self._cancelling.clear()
            raise MoveCancelledError(f"move to {target} cancelled by the operator; "
                                     f"table stopped at {self._after_reset()}") from None
        if not (status.state == "Idle" and self._at(status, target)):
            waited = "no ok to G4 P0" if reply is None else "G4 P0 answered"
            raise DeviceTimeoutError(f"turntable on {self.port}: {waited} after {allowance:.1f} s or more, table is "
                                     f"{status.state} at {self._work(status)}, target {target}")
        self._settle(status)
        return self._known

    def _restart_stalled_cycle(self, status: MachineStatus, target: tuple[float, float]) -> None:
        """Idle short of the target with G4 P0 unanswered: the cycle ended with the move still planned
        (a starved step buffer), and GRBL waits for a cycle start, which is a no-op with nothing planned.
        The deadline stays, so a board that lost its plan still times out."""
        log.warning("turntable on %s stopped at %s short of %s with its move unfinished; sending cycle start",
                    self.port, tuple(round(w, 3) for w in self._work(status)), target)
        self._p.line.write(b"~")

    def _after_reset(self) -> tuple[float, float]:
        """A reset from Hold:0 keeps MPos and the G54 reference: sync, restore modal state, re-read."""
        proto, cfg = self._p, self.config
        proto.line.write(b"\n")
        proto.await_reply("(empty line)", time.monotonic() + cfg.reply_timeout_s)
        set_modal_state(self._p, self.config.reply_timeout_s)
        self._settle(self._read_reference())
        return self._known

    def recover(self) -> Recovery:
        """Bring the table back after a vanished port, a board reset, or an alarm; see `recovery`."""
        return TurntableRecovery(self).run()

    def rehome(self) -> tuple[float, float]:
        """Home now ($H), blocking; the G54 reference then stands on the switches again."""
        with self._io:
            self._p.drain()
            self._flight = (self._machine(self._known), self._machine(self._known))
            self._p.command("$H", self.config.home_timeout_s)  # startup lines run again after homing
            set_modal_state(self._p, self.config.reply_timeout_s)
            self._settle(self._read_reference())
            self._loss = "none"
            self.position_exact = True
            return self._known
