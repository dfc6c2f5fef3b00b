"""The emulator's `$` system commands: $$, $I, $G, $#, $N, $Nx=line, $C, $H, $X, $J=, $x=value.

As in GRBL 1.1h's system.c: `$$` is refused (error:8) during a cycle or hold; `$#`, `$I`, `$N`,
`$H` and setting writes only run in Idle or Alarm; `$G`, `$C` and `$X` run in any state.

Kept beside the firmware core and operating on it, because these are the firmware's own commands;
split out only to keep each file readable.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from sim.grbl_gcode import GcodeError, parse_block
from sim.grbl_motion import PlannerBlock

if TYPE_CHECKING:
    from sim.grbl_firmware import GrblFirmware

_INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}
_INFO = {
    "grbl": ["[VER:1.1h.20190830:]", "[OPT:V,15,128]"],
    "grblhal": ["[VER:1.1f.20230917:]", "[OPT:VNMHS,35,1024,3,0]", "[FIRMWARE:grblHAL]"],
}
_HELP = "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"
_SETTING = re.compile(r"(\d+)=(.*)")
_STARTUP = re.compile(r"N(\d+)=(.*)")


def _fmt(number: int, value: float) -> str:
    return f"${number}={int(value)}" if number in _INT_SETTINGS else f"${number}={value:.3f}"


def _triple(values: list[float]) -> str:
    return ",".join(f"{v:.3f}" for v in values)


def run_system_command(fw: GrblFirmware, cmd: str, now: float) -> None:
    """Execute `$<cmd>` (already upper-cased, spaces removed) and queue its reply."""
    busy = fw._busy()
    if cmd == "":
        fw._reply([_HELP])
    elif cmd == "$":
        if busy:
            return fw._error(8)
        fw._reply([_fmt(n, v) for n, v in sorted(fw.settings.items())])
    elif cmd == "G":
        feed = fw._feed or 0.0
        units = 20 if fw._inches else 21
        fw._reply([f"[GC:G{fw._motion} G54 G17 G{units} G{90 if fw._absolute else 91} G94 M5 M9 T0 F{feed:g} S0]"])
    elif cmd == "C":
        _check_mode(fw, now)
    elif cmd in ("I", "#", "N") and fw._state not in ("Idle", "Alarm"):
        fw._error(8)
    elif cmd == "I":
        fw._reply(list(_INFO[fw.flavour]))
    elif cmd == "#":
        zero = _triple([0.0] * len(fw._g92))
        coords = [f"[G54:{_triple(fw.g54)}]"] + [f"[G{n}:{zero}]" for n in (55, 56, 57, 58, 59, 28, 30)]
        fw._reply(coords + [f"[G92:{_triple(fw._g92)}]", "[TLO:0.000]", f"[PRB:{zero}:0]"])
    elif cmd == "N":
        fw._reply([f"$N{i}={line}" for i, line in enumerate(fw.startup_lines)])
    elif (match := _STARTUP.fullmatch(cmd)) is not None:
        _store_startup_line(fw, int(match.group(1)), match.group(2), now)
    elif cmd == "X":
        if fw._state == "Alarm":
            fw._state = "Idle"
            fw._reply(["[MSG:Caution: Unlocked]"])
        else:
            fw._reply_ok()
    elif cmd == "H":
        if not fw.settings[22]:
            return fw._error(5)
        if busy:
            return fw._error(8)
        fw._blocked = True  # the ok comes when homing completes
        fw._queue.append(PlannerBlock("home", tuple(0.0 for _ in fw._g92)))
        fw._start_next(now)
    elif cmd.startswith("J="):
        _jog(fw, cmd[2:], now)
    elif (match := _SETTING.fullmatch(cmd)) is not None:
        _write_setting(fw, int(match.group(1)), match.group(2), busy)
    else:
        fw._error(3)


def _check_mode(fw: GrblFirmware, now: float) -> None:
    """`$C` toggles check mode; leaving it resets the board (GRBL's mc_reset), so a banner follows."""
    if fw._state == "Check":
        fw._reply(["[MSG:Disabled]"])
        fw._soft_reset(now)
    elif fw._state != "Idle":
        fw._error(8)
    else:
        fw._state = "Check"
        fw._reply(["[MSG:Enabled]"])


def _store_startup_line(fw: GrblFirmware, number: int, line: str, now: float) -> None:
    """`$Nx=line`: Idle only; GRBL runs the line once to validate it (so it takes effect now too)."""
    if fw._state != "Idle":
        return fw._error(8)
    if number >= len(fw.startup_lines):
        return fw._error(3)
    if line:
        before = len(fw._out)
        fw._gcode(line, now)
        if bytes(fw._out[before:]).startswith(b"error"):
            return
        del fw._out[before:]
    fw.startup_lines[number] = line
    fw._reply_ok()


def _jog(fw: GrblFirmware, text: str, now: float) -> None:
    if fw._state not in ("Idle", "Jog"):
        return fw._error(8)
    try:
        block = parse_block(text, fw._absolute, fw._motion, fw._feed, jog=True)
    except GcodeError as exc:
        return fw._error(exc.code)
    target = tuple((v + g if block.absolute else p + v) if v is not None else p
                   for v, p, g in zip(block.axes, fw._planned, fw.wco()))
    if not fw._within_travel(target):
        return fw._error(15)
    fw.enqueue(PlannerBlock("jog", target, block.feed), now)
    fw._reply_ok()


def _write_setting(fw: GrblFirmware, number: int, text: str, busy: bool) -> None:
    if busy:
        return fw._error(8)
    if number not in fw.settings:
        return fw._error(3)
    try:
        value = float(text)
    except ValueError:
        return fw._error(2)
    if value < 0:
        return fw._error(4)
    if number == 20 and value and not fw.settings[22]:
        return fw._error(10)
    fw.settings[number] = value
    fw._reply_ok()
