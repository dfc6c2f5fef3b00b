"""A GRBL 1.1h / grblHAL firmware emulator: bytes in, bytes out, motion in (scaled) real time.

Reproduces what docs/rig.md records of real firmware: banner on reset, one `ok`/`error:N` per line,
realtime bytes, key-based status reports, `$I $$ $G $# $N $C $H $X $J=` (error:8 where GRBL refuses
them while moving), G90/G91/G0/G1/G4/G10 L20/G20/G21/G92 with F, ALARM:3 on reset during motion
(after the `ok` of a pending G4), critical ALARM:2 soft-limit and ALARM:1 hard-limit states that
ignore everything until 0x18 (which then answers the line that tripped ALARM:2), boot into Alarm when homing is enabled, and `$N` startup lines run
after each reset with their `>line:ok` echo. Settings, the G54 offset and `$N` lines are EEPROM:
they survive resets and power cycles. A new board has GRBL's factory settings. The clock is evaluated lazily:
every `write`/`read`/`position` call first advances the machine to `clock()`, so no thread is needed
here; the links in `sim.grbl_links` pump it.

Two positions are kept apart: the firmware's step counter (MPos) and the physical stage (what a
camera sees). They differ only after a power cycle, which zeroes the counter where the stage stands.
"""

from __future__ import annotations

import random
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from sim.grbl_gcode import GcodeError, parse_block
from sim.grbl_motion import PlannerBlock, Segment, decel_segment, move_segment, timed_segment
from sim.grbl_system import run_system_command

AXES = 3  # X turntable (degrees), Y tilt arm (degrees), Z unused
FACTORY_SETTINGS: dict[int, float] = {  # GRBL 1.1h defaults.h (DEFAULTS_GENERIC), as a fresh EEPROM lists them
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}
# The turntable rig's settings (what shared/tools/grbl-sim/EEPROM.rig.DAT holds): degrees, not mm.
RIG_SETTINGS: dict[int, float] = {100: 44.444, 101: 44.444, 110: 3600.0, 111: 1800.0, 120: 180.0, 121: 90.0}
BANNERS = {"grbl": "Grbl 1.1h ['$' for help]", "grblhal": "GrblHAL 1.1f ['$' or '$HELP' for help]"}
_UNLOCK_MSG = "[MSG:'$H'|'$X' to unlock]"
_FEED_OVERRIDE = {0x90: None, 0x91: 10, 0x92: -10, 0x93: 1, 0x94: -1}  # None: back to 100 %


@dataclass
class Faults:
    """Fault injection knobs; move counts are from now (1 = the next move), each fires once."""

    garble_status: int = 0  # the next N status reports come out truncated or corrupted
    drop_ok: int = 0  # the next N `ok` replies are never sent
    reset_on_move: int | None = None  # the board power-cycles halfway through that move
    alarm_on_move: int | None = None  # a hard limit (ALARM:1) trips halfway through that move
    vanish_on_move: int | None = None  # the USB link drops halfway through that move
    starve_on_move: int | None = None  # the step buffer runs dry halfway: Idle there, the rest waits for `~`
    replug_after_s: float | None = 0.2  # wall seconds until a vanished link returns (None: never)
    ignore_resets: int = 0  # the next N ctrl-x bytes are lost, as while a board is still booting


class GrblFirmware:
    """One emulated controller board; thread-safe (the camera asks `position()` from its own thread)."""

    def __init__(self, *, flavour: Literal["grbl", "grblhal"] = "grbl", homing: bool = False,
                 soft_limits: bool = False, time_scale: float = 1.0, settings: dict[int, float] | None = None,
                 clock: Callable[[], float] = time.monotonic, seed: int = 0) -> None:
        if flavour not in BANNERS:
            raise ValueError(f"unknown firmware flavour {flavour!r}; expected one of {sorted(BANNERS)}")
        if not time_scale > 0:
            raise ValueError(f"time_scale must be positive, got {time_scale!r}")
        self.flavour = flavour
        self.time_scale = time_scale
        self.settings = dict(FACTORY_SETTINGS) | (settings or {})
        self.g54 = [0.0] * AXES  # EEPROM, like the settings and the startup lines
        self.startup_lines = ["", ""]
        self.settings[22] = 1 if homing else self.settings[22]
        self.settings[20] = 1 if soft_limits else self.settings[20]
        self.faults = Faults()
        self.generation = 0  # bumps each time the link drops, so open handles know they are dead
        self.plugged = True
        self._clock = clock
        self._rng = random.Random(seed)
        self._lock = threading.RLock()
        self._out = bytearray()
        self._mpos = [0.0] * AXES
        self._phys_offset = [0.0] * AXES
        self._replug_at: float | None = None
        self._event: tuple[float, str] | None = None
        self._boot(self._clock(), power_on=True)

    # ---- the wire -------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """Bytes from the host. Realtime bytes act at once; others build lines."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            if not self.plugged:
                return
            for byte in data:
                if byte == 0x18 and self.faults.ignore_resets > 0:
                    self.faults.ignore_resets -= 1
                elif byte == 0x18:
                    self._soft_reset(now)
                elif self._critical:
                    continue  # rig.md: everything is ignored until 0x18
                elif byte == ord("?"):
                    self._out += self._status_line(now).encode() + b"\r\n"
                elif byte == ord("!"):
                    self._hold(now, "Hold")
                elif byte == 0x84:
                    self._hold(now, "Door")
                elif byte == ord("~"):
                    self._cycle_start(now)
                elif byte == 0x85:
                    self._jog_cancel(now)
                elif byte in _FEED_OVERRIDE:
                    self._override(byte)
                elif byte >= 0x80:
                    continue
                elif byte in (0x0A, 0x0D):
                    self._lines.append(self._rx.decode("ascii", errors="replace") if len(self._rx) < 80 else None)
                    self._rx.clear()
                else:
                    self._rx.append(byte)
            self._process_lines(now)

    def read(self) -> bytes:
        """Everything the board has sent since the last call (empty while unplugged)."""
        with self._lock:
            self._advance(self._clock())
            out, self._out = bytes(self._out), bytearray()
            return out if self.plugged else b""

    def position(self) -> tuple[float, float]:
        """Where the stage physically is now: (turntable X, tilt Y) in degrees."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            pos = self._machine(now)
            return (pos[0] + self._phys_offset[0], pos[1] + self._phys_offset[1])

    @property
    def state(self) -> str:
        with self._lock:
            self._advance(self._clock())
            return self._state

    def power_cycle(self) -> None:
        """The board resets itself (brown-out, watchdog): the step counter restarts at zero."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            self._halt(now)
            self._boot(now, power_on=True)

    def unplug(self, replug_after_s: float | None) -> None:
        """The USB link drops now; the board is unpowered until replugged (None: stays away)."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            self._unplug(now, replug_after_s)

    # ---- clock ----------------------------------------------------------------------------
    def _tau(self, seg: Segment, now: float) -> float:
        return (now - seg.t0) / self.time_scale

    def _machine(self, now: float) -> list[float]:
        return list(self._seg.position(self._tau(self._seg, now))) if self._seg else list(self._mpos)

    def _advance(self, now: float) -> None:
        while True:
            if not self.plugged:
                if self._replug_at is None or now < self._replug_at:
                    return
                self.plugged, t = True, self._replug_at
                self._replug_at = None
                self._boot(t, power_on=True)
                continue
            seg = self._seg
            if seg is None:
                return
            t_end = seg.t0 + seg.duration * self.time_scale
            if self._event is not None and self._event[0] <= min(t_end, now):
                self._fire(*self._event)
                continue
            if t_end > now:
                return
            self._finish(seg, t_end)

    def _fire(self, t: float, kind: str) -> None:
        self._event = None
        if kind == "starve":
            return self._starve(t)
        self._halt(t)
        if kind == "reset":
            self._boot(t, power_on=True)
        elif kind == "alarm":
            self._state, self._critical = "Alarm", True
            self._out += b"ALARM:1\r\n[MSG:Reset to continue]\r\n"
        else:
            self._unplug(t, self.faults.replug_after_s)

    def _unplug(self, now: float, replug_after_s: float | None) -> None:
        self._halt(now)
        self.plugged = False
        self.generation += 1
        self._out.clear()
        self._replug_at = None if replug_after_s is None else now + replug_after_s

    # ---- machine state ----------------------------------------------------------------------
    def _boot(self, now: float, *, power_on: bool) -> None:
        """Reset or power-on: modal state, queue and work offset cleared; power-on also zeroes MPos."""
        if power_on:
            self._phys_offset = [p + m for p, m in zip(self._phys_offset, self._mpos)]
            self._mpos = [0.0] * AXES
            self._state = "Alarm" if self.settings[22] else "Idle"
        self._seg: Segment | None = None
        self._queue: deque[PlannerBlock] = deque()
        self._lines: deque[str | None] = deque()
        self._rx = bytearray()
        self._blocked = False  # a G4 or $H is running: later lines wait
        self._critical = False
        self._ok_on_reset = False
        self._sub = 0  # Hold:N / Door:N
        self._cancel_jog = False
        self._g92 = [0.0] * AXES
        self._planned = list(self._mpos)
        self._absolute, self._motion, self._feed, self._inches = True, 0, None, False
        self._feed_pct = 100  # feed override, back to 100 % on every reset
        self._ovr_due = True  # real GRBL: WCO on the first report after a reset, Ov on the next
        self._reports, self._wco_dirty = 0, True
        self._event = None
        self._out += f"\r\n{BANNERS[self.flavour]}\r\n".encode()
        if power_on:
            self._after_boot(now)

    def _after_boot(self, now: float) -> None:
        """Alarm: the unlock message; otherwise run the `$N` startup lines, echoing `>line:status`."""
        if self._state == "Alarm":
            self._out += f"{_UNLOCK_MSG}\r\n".encode()
            return
        for line in self.startup_lines:
            if line:
                before = len(self._out)
                self._gcode("".join(line.split()).upper(), now)
                reply = bytes(self._out[before:]).decode().strip() or "ok"
                del self._out[before:]
                self._out += f">{line}:{reply}\r\n".encode()

    def _soft_reset(self, now: float) -> None:
        moving = self._seg is not None and self._seg.kind != "dwell"
        homing = moving and self._seg.kind == "home"
        was_alarm = self._state == "Alarm"
        dwell_pending = any(block.kind == "dwell" for block in self._queue)
        self._halt(now)
        if self._ok_on_reset:
            self._reply_ok()
        if moving:
            if dwell_pending:
                self._out += b"ok\r\n"  # real GRBL answers the pending G4 P0 before the alarm
            self._out += b"ALARM:6\r\n" if homing else b"ALARM:3\r\n"
        self._boot(now, power_on=False)
        self._state = "Alarm" if moving or was_alarm else "Idle"
        self._after_boot(now)

    def _stop_here(self, now: float) -> None:
        """End the running segment where the stage is now; the counter keeps the whole steps taken."""
        self._mpos = list(self._on_steps(self._machine(now)))
        self._seg = None

    def _starve(self, now: float) -> None:
        """The stepper ran out of segments (grbl-sim on a loaded host): GRBL ends the cycle there and
        keeps the rest of the block planned, so a queued G4 P0 waits until a cycle start resumes it."""
        self._stop_here(now)
        self._state = "Idle"

    def _halt(self, now: float) -> None:
        """Stop dead (reset, alarm, power loss): the counter keeps the steps taken so far."""
        self._stop_here(now)
        self._queue.clear()
        self._planned = list(self._mpos)
        self._blocked = False
        self._lines.clear()

    def _start_next(self, t: float) -> None:
        while self._queue:
            block = self._queue[0]
            if block.kind == "dwell":
                self._seg = timed_segment("dwell", t, tuple(self._mpos), tuple(self._mpos), block.seconds)
                return
            if block.kind == "home":
                seconds = max(abs(m) for m in self._mpos) / (self.settings[25] / 60.0) + 0.5
                self._seg = timed_segment("home", t, tuple(self._mpos), block.target, seconds)
                self._state = "Home"
                return
            rates = tuple(self.settings[110 + i] for i in range(AXES))
            accels = tuple(self.settings[120 + i] for i in range(AXES))
            feed = block.feed
            if feed is not None and block.kind == "move":  # jogs ignore the feed override, as in GRBL
                feed *= self._feed_pct / 100.0
            seg = move_segment(t, tuple(self._mpos), block.target, rates, accels, feed)
            if seg.length == 0.0:
                self._queue.popleft()
                continue
            self._seg = seg
            self._state = "Jog" if block.kind == "jog" else "Run"
            self._arm_faults(seg)
            return
        self._seg = None
        if self._state in ("Run", "Jog", "Home"):
            self._state = "Idle"

    def _arm_faults(self, seg: Segment) -> None:
        midpoint = seg.t0 + 0.5 * seg.duration * self.time_scale
        for knob, kind in (("reset_on_move", "reset"), ("alarm_on_move", "alarm"), ("vanish_on_move", "vanish"),
                           ("starve_on_move", "starve")):
            left = getattr(self.faults, knob)
            if left is not None:
                setattr(self.faults, knob, None if left <= 1 else left - 1)
                if left <= 1:
                    self._event = (midpoint, kind)

    def _finish(self, seg: Segment, t: float) -> None:
        self._mpos = list(seg.end())
        self._seg = None
        if seg.kind == "decel":
            self._sub = 0
            if self._cancel_jog:
                self._cancel_jog = False
                self._queue.clear()
                self._planned = list(self._mpos)
                self._state = "Idle"
            return
        block = self._queue.popleft()
        if block.kind == "home":
            self._phys_offset = [round(p / 360.0) * 360.0 if i == 0 else 0.0 for i, p in enumerate(
                m + o for m, o in zip(self._mpos, self._phys_offset))]
            self._mpos = [0.0] * AXES
            self._planned = [0.0] * AXES
        if block.kind in ("home", "dwell"):
            self._blocked = False
            self._reply_ok()
        self._start_next(t)
        self._process_lines(t)

    def _hold(self, now: float, state: str) -> None:
        seg = self._seg
        if self._state in ("Run", "Jog") and seg is not None and seg.kind == "move":
            tau = self._tau(seg, now)
            self._seg = decel_segment(now, seg.position(tau), seg.direction, seg.velocity(tau), seg.accel)
            self._state, self._sub = state, 1
        elif self._state == "Idle" and seg is None:
            self._state, self._sub = state, 0

    def _cycle_start(self, now: float) -> None:
        if self._state in ("Hold", "Door") and self._sub == 0:  # ~ during Hold:1 is ignored
            self._state = "Idle"
            self._start_next(now)
        elif self._state == "Idle" and self._seg is None and self._queue:  # planned motion that is not running
            self._start_next(now)

    def _override(self, byte: int) -> None:
        """Feed override (0x90-0x94), 10-200 %: here it applies from the next block GRBL plans."""
        step = _FEED_OVERRIDE[byte]
        self._feed_pct = 100 if step is None else min(200, max(10, self._feed_pct + step))
        self._ovr_due = True  # the next report without WCO carries Ov, as GRBL's does after a change

    def _jog_cancel(self, now: float) -> None:
        if self._state == "Jog":
            self._hold(now, "Jog")
            self._cancel_jog = True

    # ---- lines ------------------------------------------------------------------------------
    def _reply_ok(self) -> None:
        if self.faults.drop_ok > 0:
            self.faults.drop_ok -= 1
        else:
            self._out += b"ok\r\n"

    def _reply(self, lines: list[str]) -> None:
        self._out += "".join(f"{line}\r\n" for line in lines).encode()
        self._reply_ok()

    def _error(self, code: int) -> None:
        self._out += f"error:{code}\r\n".encode()

    def _process_lines(self, now: float) -> None:
        while self._lines and not self._blocked and not self._critical:
            line = self._lines.popleft()
            if line is None:
                self._error(11)
                continue
            text = "".join(line.split()).upper() if not line.startswith("$") else line.strip()
            if text == "":
                self._reply_ok()
            elif text.startswith("$"):
                self._system(text[1:], now)
            elif self._state in ("Alarm", "Jog"):
                self._error(9)
            else:
                self._gcode(text, now)

    def _busy(self) -> bool:
        return self._seg is not None or self._state in ("Run", "Hold", "Jog", "Home", "Door")

    def _system(self, cmd: str, now: float) -> None:
        run_system_command(self, "".join(cmd.split()).upper(), now)

    def _gcode(self, text: str, now: float) -> None:
        try:
            block = parse_block(text, self._absolute, self._motion, self._feed, inches=self._inches)
        except GcodeError as exc:
            self._error(exc.code)
            return
        self._inches = block.inches
        if self._state == "Check":  # check mode: parsed and answered, nothing executed
            self._absolute, self._motion, self._feed = block.absolute, block.motion, block.feed
            return self._reply_ok()
        wco = self.wco()
        if block.g10_l20 is not None:
            self.g54 = [p - g - v if v is not None else c for p, g, v, c in zip(self._planned, self._g92, block.g10_l20, self.g54)]
            self._wco_dirty = True
        if block.dwell is not None:
            self._queue.append(PlannerBlock("dwell", tuple(self._planned), seconds=block.dwell))
            self._blocked = True
        if block.g92 is not None:
            self._g92 = [p - c - v if v is not None else g for p, c, v, g in zip(self._planned, self.g54, block.g92, self._g92)]
            self._wco_dirty = True
        if block.g92_clear:
            self._g92, self._wco_dirty = [0.0] * AXES, True
        self._absolute, self._motion, self._feed = block.absolute, block.motion, block.feed
        if block.axes is not None:
            target = tuple((v + o if block.absolute else p + v) if v is not None else p
                           for v, p, o in zip(block.axes, self._planned, wco))
            if not self._within_travel(target):
                self._halt(now)
                self._state, self._critical = "Alarm", True
                self._out += b"ALARM:2\r\n[MSG:Reset to continue]\r\n"
                self._ok_on_reset = True  # GRBL answers the tripping line only once reset frees it
                return
            self.enqueue(PlannerBlock("move", target, block.feed if block.motion == 1 else None), now)
        if not self._blocked:
            self._reply_ok()
        elif self._seg is None:
            self._start_next(now)

    def wco(self) -> list[float]:
        """Work coordinate offset: G54 (EEPROM) plus G92 (cleared by every reset)."""
        return [c + g for c, g in zip(self.g54, self._g92)]

    def _within_travel(self, target: tuple[float, ...]) -> bool:
        """Soft limits: GRBL's machine travel is [-$13x, 0] (homing sets the origin at the top)."""
        if not self.settings[20]:
            return True
        return all(-self.settings[130 + i] - 1e-6 <= t <= 1e-6 for i, t in enumerate(target))

    def _on_steps(self, pos: list[float] | tuple[float, ...]) -> tuple[float, ...]:
        """Snap to whole motor steps ($100-$102): targets and stops are step counts in GRBL."""
        return tuple(round(p * self.settings[100 + i]) / self.settings[100 + i] for i, p in enumerate(pos))

    def enqueue(self, block: PlannerBlock, now: float) -> None:
        """Plan a block (target snapped to steps); it starts at once when the machine is idle.

        The parser's position stays the programmed one, unsnapped, as GRBL's gc_state.position does.
        """
        self._planned = list(block.target)
        block.target = self._on_steps(block.target)
        self._queue.append(block)
        if self._seg is None and self._state not in ("Hold", "Door"):
            self._start_next(now)

    # ---- reports ----------------------------------------------------------------------------
    def _status_line(self, now: float) -> str:
        pos = self._machine(now)
        steps = [self.settings[100 + i] for i in range(AXES)]
        mpos = ",".join(f"{round(p * s) / s:.3f}" for p, s in zip(pos, steps))
        speed = self._seg.velocity(self._tau(self._seg, now)) * 60.0 if self._seg else 0.0
        state = f"{self._state}:{self._sub}" if self._state in ("Hold", "Door") else self._state
        fields = [state, f"MPos:{mpos}"]
        if self.flavour == "grblhal":
            fields.append(f"Bf:{35 - len(self._queue)},1023")
        fields.append(f"FS:{speed:.0f},0")
        if self._reports % 10 == 0 or self._wco_dirty:
            fields.append("WCO:" + ",".join(f"{g:.3f}" for g in self.wco()))
            self._wco_dirty = False
        elif self._reports % 10 == 5 or self._ovr_due:
            self._ovr_due = False
            fields.append(f"Ov:{self._feed_pct},100,100")
        self._reports += 1
        line = "<" + "|".join(fields) + ">"
        if self.faults.garble_status > 0:
            self.faults.garble_status -= 1
            line = self._garble(line)
        return line

    def _garble(self, line: str) -> str:
        """Line noise: a report cut short, or a digit hit by a flipped bit."""
        if self._rng.random() < 0.5:
            return line[: self._rng.randrange(1, len(line) - 1)]
        digits = [i for i, c in enumerate(line) if c.isdigit()]
        i = self._rng.choice(digits)
        return line[:i] + chr(ord(line[i]) ^ 0x40) + line[i + 1:]
