"""GRBL line protocol: send one line, wait for its `ok`/`error:N`, classify whatever else arrives.

Replies end with `\\r\\n`; between a line and its reply the firmware may interleave status reports,
`[...]` info lines, `ALARM:N` and, if the board reset itself, its banner. Each of those is turned
into data or a typed exception here, so the driver above only sees outcomes.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

from station.errors import DeviceTimeoutError
from station.turntable.errors import GarbledStatusError, GrblAlarm, GrblError, NotGrblError, UnexpectedResetError
from station.turntable.link import SerialLine
from station.turntable.status import MachineStatus, parse_status

log = logging.getLogger(__name__)
BANNER = re.compile(r"^(Grbl|GrblHAL) (\d+\.\d+\w*) \[.*\]$")
_CODE = re.compile(r"^(error|ALARM):(\d+)$")


@dataclass(frozen=True)
class Handshake:
    """What a reset printed: banner flavour and version, alarms raised, `$N` startup lines run."""

    flavour: str
    version: str
    alarms: tuple[int, ...]  # ALARM:3 here: the reset caught the table moving, its position is lost
    startup: tuple[str, ...]  # e.g. "G20:ok": each line the firmware ran and its own status


@dataclass(frozen=True)
class FirmwareInfo:
    """Who answered: banner flavour and version, `$I` build info, `$$` settings."""

    flavour: str  # "Grbl" or "GrblHAL"
    version: str  # banner version, e.g. "1.1h"
    build: str  # [VER:...] text
    options: str  # [OPT:...] text
    settings: dict[int, float]
    startup_lines: tuple[str, ...] = ()  # `$N` lines stored in EEPROM, run after every reset


class GrblProtocol:
    """Reply handling over one SerialLine; `on_status` sees every well-formed status report."""

    def __init__(self, line: SerialLine, on_status: Callable[[MachineStatus], None]) -> None:
        self.line = line
        self.port = line.port
        self._on_status = on_status
        self.garbled = 0  # garbled status reports skipped while waiting (counted, never trusted)

    def classify(self, text: str) -> tuple[str, object]:
        """Sort one received line: ok / error / status / info / noise; ALARM and banner raise."""
        text = text.strip()
        if text == "ok":
            return "ok", None
        code = _CODE.match(text)
        if code and code.group(1) == "error":
            return "error", int(code.group(2))
        if code:
            raise GrblAlarm(int(code.group(2)), self.port)
        if BANNER.match(text):
            raise UnexpectedResetError(f"turntable on {self.port} reset itself mid-session (banner {text!r})")
        if text.startswith("<"):
            try:
                status = parse_status(text)
            except GarbledStatusError:
                self.garbled += 1
                return "garbled", text
            self._on_status(status)
            return "status", status
        if text.startswith("[") and text.endswith("]"):
            return "info", text
        if text:
            log.warning("ignoring unexpected line from %s: %r", self.port, text)
        return "noise", text

    def await_reply(self, sent: str, deadline: float, *, poll_s: float | None = None,
                    adjust: Callable[[MachineStatus, float], float] | None = None) -> list[str] | None:
        """Info lines of the reply to `sent`, or None if no reply came by `deadline`.

        With `poll_s`, a `?` goes out whenever the line is quiet that long (status fallback, <= 5 Hz);
        `adjust(status, deadline)` returns a new deadline: later during a feed hold (the operator's
        time, not a fault), sooner once the table is seen idle at its target (the `ok` was lost).
        """
        info: list[str] = []
        next_poll = time.monotonic() + poll_s if poll_s else float("inf")
        while True:
            text = self.line.read_line(min(deadline, next_poll))
            now = time.monotonic()
            if text is None:
                if now >= deadline:
                    return None
                self.line.write(b"?")
                next_poll = now + poll_s
                continue
            kind, value = self.classify(text)
            if kind == "ok":
                return info
            if kind == "error":
                raise GrblError(int(value), sent, self.port)
            if kind == "info":
                info.append(str(value))
            if kind == "status" and adjust is not None:
                deadline = adjust(value, deadline)  # type: ignore[arg-type]

    def drain(self) -> None:
        """Read what already arrived unasked: a banner or ALARM here must stop the next line going out."""
        while (text := self.line.read_line(0.0)) is not None:
            self.classify(text)

    def command(self, text: str, timeout_s: float) -> list[str]:
        """Send one line and return its info lines; a missing reply is a DeviceTimeoutError."""
        self.line.write(text.encode("ascii") + b"\n")
        info = self.await_reply(text, time.monotonic() + timeout_s)
        if info is None:
            raise DeviceTimeoutError(f"turntable on {self.port} did not answer {text!r} within {timeout_s:g} s")
        return info

    def query_status(self, timeout_s: float) -> MachineStatus:
        """Send `?` and parse its report; a garbled report is refused and asked for once more."""
        garbled = ""
        for _attempt in (1, 2):
            self.line.write(b"?")
            deadline = time.monotonic() + timeout_s
            while True:
                text = self.line.read_line(deadline)
                if text is None:
                    raise DeviceTimeoutError(f"turntable on {self.port} sent no status report within {timeout_s:g} s")
                kind, value = self.classify(text)
                if kind == "status":
                    return value  # type: ignore[return-value]
                if kind == "garbled":
                    garbled = str(value)
                    break
        raise GarbledStatusError(f"turntable on {self.port} sent two garbled status reports in a row, last {garbled!r}")

    def probe(self, timeout_s: float) -> MachineStatus | None:
        """Ask `?` before any reset: a table still moving (a killed driver, a lost reply) must be held first."""
        self.line.discard_input()
        self.line.write(b"?")
        deadline = time.monotonic() + timeout_s
        while (text := self.line.read_line(deadline)) is not None:
            if text.strip().startswith("<"):
                try:
                    return parse_status(text)
                except GarbledStatusError:
                    return None
        return None

    def handshake(self, timeout_s: float, retry_s: float = 1.0) -> Handshake:
        """Soft-reset (0x18) until a banner comes, then sync with an empty line.

        A board that has just powered up ignores input for about a second and prints its own banner
        late, so the reset is repeated every `retry_s`. Each queued reset flushes GRBL's receive
        buffer, so the sync line goes out only once banners have stopped for a while, and again if
        another banner follows it; its `ok` then comes after every banner, `ALARM:3` and
        `>startup line:ok` echo the resets caused.
        """
        self.line.discard_input()
        self.line.heard.clear()
        deadline = time.monotonic() + timeout_s
        banner: re.Match[str] | None = None
        alarms: list[int] = []
        startup: list[str] = []

        def note(text: str) -> bool:
            """Record one line; True if it was a banner."""
            nonlocal banner
            text = text.strip()
            code = _CODE.match(text)
            if code and code.group(1) == "ALARM":
                alarms.append(int(code.group(2)))  # a reset mid-move: ALARM:3 comes before the banner
            elif text.startswith(">"):
                startup.append(text[1:])  # `>G20:ok`: a $N startup line the firmware ran after the reset
            elif (match := BANNER.match(text)) is not None:
                banner = match
                startup.clear()
                return True
            return False

        while banner is None:
            self.line.write(b"\x18")
            retry = min(deadline, time.monotonic() + retry_s)
            while banner is None and (text := self.line.read_line(retry)) is not None:
                note(text)
            if banner is None and time.monotonic() >= deadline:
                heard = bytes(self.line.heard).decode("ascii", errors="replace").strip()
                if heard:
                    raise NotGrblError(self.port, heard[:80])
                raise DeviceTimeoutError(f"no answer from {self.port} within {timeout_s:g} s of a reset; "
                                         "is a GRBL turntable connected and powered?")
        quiet_s = retry_s / 2.0
        sync_deadline = max(deadline, time.monotonic() + 2.0 * retry_s)
        while time.monotonic() < sync_deadline:
            while (text := self.line.read_line(time.monotonic() + quiet_s)) is not None:
                note(text)  # later banners, their echoes, a stray `ok` of an earlier sync: all before ours
            self.line.write(b"\n")
            while (text := self.line.read_line(sync_deadline)) is not None:
                code = _CODE.match(text.strip())
                if text.strip() == "ok":
                    return Handshake(banner.group(1), banner.group(2), tuple(alarms), tuple(startup))
                if code and code.group(1) == "error":
                    raise GrblError(int(code.group(2)), "(empty line)", self.port)
                if note(text):
                    break  # one more reset came after the sync line and may have flushed it
        raise DeviceTimeoutError(f"turntable on {self.port} sent its banner but did not answer an empty line")

    def identify(self, flavour: str, version: str, timeout_s: float) -> FirmwareInfo:
        """`$I` build info, `$$` settings and `$N` startup lines (all refused with error:8 while moving)."""
        info = self.command("$I", timeout_s)
        build = next((s[5:-1] for s in info if s.startswith("[VER:")), "")
        options = next((s[5:-1] for s in info if s.startswith("[OPT:")), "")
        settings: dict[int, float] = {}
        for text in self.listing("$$", timeout_s):
            match = re.match(r"^\$(\d+)=([-+0-9.]+)", text)
            if match:
                settings[int(match.group(1))] = float(match.group(2))
        startup = (line.split("=", 1)[1] for line in self.listing("$N", timeout_s) if line.startswith("$N") and "=" in line)
        return FirmwareInfo(flavour, version, build, options, settings, tuple(s for s in startup if s))

    def listing(self, command: str, timeout_s: float) -> list[str]:
        """Lines of a `$` listing (`$N`, `$$`) that are not status, info or replies."""
        self.line.write(command.encode("ascii") + b"\n")
        deadline = time.monotonic() + timeout_s
        lines: list[str] = []
        while True:
            text = self.line.read_line(deadline)
            if text is None:
                raise DeviceTimeoutError(f"turntable on {self.port} did not finish {command!r} within {timeout_s:g} s")
            if text.strip().startswith("$"):
                lines.append(text.strip())
                continue
            kind, value = self.classify(text)
            if kind == "ok":
                return lines
            if kind == "error":
                raise GrblError(int(value), command, self.port)
