"""Parse GRBL 1.1 / grblHAL `?` status reports by key, never by position.

A report looks like `<Idle|MPos:0.000,0.000,0.000|FS:0,0|Pn:XY|WCO:0.000,0.000,0.000>`. Every
`|Key:value` field is optional (WCO and Ov come only on some reports; grblHAL adds Bf, A, TLR and
puts Bf before FS), so fields are looked up by key and unknown keys are kept, not rejected. A line
that is truncated or has a corrupted number is refused with GarbledStatusError: a half-read
position must never be mistaken for where the table is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from station.turntable.errors import GarbledStatusError

STATES = ("Idle", "Run", "Jog", "Hold", "Alarm", "Check", "Home", "Door", "Sleep", "Tool")
# Keys whose value is a comma list of numbers; everything else is kept as text.
_NUMERIC_KEYS = {"MPos", "WPos", "WCO", "FS", "F", "Bf", "Ov"}


@dataclass(frozen=True)
class MachineStatus:
    """One status report. Positions are per axis in report order (X, Y, Z[, A...])."""

    state: str  # one of STATES
    substate: int | None = None  # Hold:0 stopped / Hold:1 decelerating; Door:N
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    wco: tuple[float, ...] | None = None
    feed: float | None = None  # current feed rate, units/min
    spindle: float | None = None
    buffer: tuple[int, int] | None = None  # Bf: free planner blocks, free rx bytes
    pins: str = ""  # Pn: active input pins, e.g. "XY"
    overrides: tuple[int, ...] | None = None  # Ov: feed, rapid, spindle percent
    accessories: str = ""  # A: spindle/coolant flags
    extra: dict[str, str] = field(default_factory=dict)  # keys this parser does not interpret

    def work_position(self, wco: tuple[float, ...] | None) -> tuple[float, ...] | None:
        """Work position: WPos if reported, else MPos minus the WCO (this report's or the last seen)."""
        if self.wpos is not None:
            return self.wpos
        offset = self.wco if self.wco is not None else wco
        if self.mpos is None or offset is None:
            return None
        return tuple(m - o for m, o in zip(self.mpos, offset))

    def machine_position(self, wco: tuple[float, ...] | None) -> tuple[float, ...] | None:
        """Machine position: MPos if reported, else WPos plus the WCO."""
        if self.mpos is not None:
            return self.mpos
        offset = self.wco if self.wco is not None else wco
        if self.wpos is None or offset is None:
            return None
        return tuple(w + o for w, o in zip(self.wpos, offset))


def _numbers(key: str, text: str, line: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise GarbledStatusError(f"status field {key} has a bad number in {line!r}") from None
    if not all(abs(v) < 1e9 for v in values):
        raise GarbledStatusError(f"status field {key} is out of range in {line!r}")
    return values


def parse_status(line: str) -> MachineStatus:
    """Parse one `<...>` report; raise GarbledStatusError if it is partial or corrupted."""
    text = line.strip()
    if not (text.startswith("<") and text.endswith(">")) or text.count("<") != 1 or text.count(">") != 1:
        raise GarbledStatusError(f"status report is not one complete <...> line: {line!r}")
    parts = text[1:-1].split("|")
    state_text = parts[0]
    state, _, sub = state_text.partition(":")
    if state not in STATES:
        raise GarbledStatusError(f"unknown machine state {state_text!r} in {line!r}")
    substate = None
    if sub:
        if not sub.isdigit():
            raise GarbledStatusError(f"bad substate {state_text!r} in {line!r}")
        substate = int(sub)
    values: dict[str, tuple[float, ...]] = {}
    texts: dict[str, str] = {}
    for part in parts[1:]:
        key, colon, value = part.partition(":")
        if not key.isalpha() or (colon and not value):
            raise GarbledStatusError(f"malformed status field {part!r} in {line!r}")
        if key in values or key in texts:
            raise GarbledStatusError(f"repeated status field {key} in {line!r}")
        if key in _NUMERIC_KEYS:
            values[key] = _numbers(key, value, line)
        else:
            texts[key] = value
    if "MPos" not in values and "WPos" not in values:
        raise GarbledStatusError(f"status report has neither MPos nor WPos: {line!r}")
    axes = len(values.get("MPos", values.get("WPos", ())))
    for key in ("MPos", "WPos", "WCO"):
        if key in values and len(values[key]) != axes:
            raise GarbledStatusError(f"status field {key} has {len(values[key])} axes, expected {axes}: {line!r}")
    fs = values.get("FS", values.get("F"))
    bf = values.get("Bf")
    if bf is not None and len(bf) != 2:
        raise GarbledStatusError(f"status field Bf needs two numbers: {line!r}")
    ov = values.get("Ov")
    return MachineStatus(
        state=state,
        substate=substate,
        mpos=values.get("MPos"),
        wpos=values.get("WPos"),
        wco=values.get("WCO"),
        feed=fs[0] if fs else None,
        spindle=fs[1] if fs and len(fs) > 1 else None,
        buffer=(int(bf[0]), int(bf[1])) if bf is not None else None,
        pins=texts.pop("Pn", ""),
        overrides=tuple(int(v) for v in ov) if ov is not None else None,
        accessories=texts.pop("A", ""),
        extra=texts,
    )
