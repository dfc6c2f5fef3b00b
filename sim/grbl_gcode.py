"""G-code block parser for the GRBL emulator, returning GRBL's own error codes.

Covers what a turntable needs: G0/G1/G4/G10 L20/G90/G91/G92/G92.1, G20/G21 units (inches scale
every axis word and feed by 25.4, as GRBL does) plus the harmless modal words a sender emits (G17
G54 G94, M0-M9). Other G-codes get error:20 as the rig notes record.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)")
_AXIS_LETTERS = "XYZ"
_VALUE_LETTERS = set(_AXIS_LETTERS) | {"F", "P", "N", "S", "T", "L"}
MM_PER_INCH = 25.4
_GROUPS: dict[float, str] = {
    0: "motion", 1: "motion", 4: "non-modal", 10: "non-modal", 92: "non-modal", 92.1: "non-modal",
    90: "distance", 91: "distance", 17: "plane", 20: "units", 21: "units", 54: "wcs", 94: "feed-mode",
}
_M_CODES = {0, 1, 2, 3, 4, 5, 7, 8, 9, 30}


class GcodeError(Exception):
    """A block GRBL would refuse; `code` is the `error:N` number."""

    def __init__(self, code: int) -> None:
        super().__init__(f"error:{code}")
        self.code = code


@dataclass(frozen=True)
class Block:
    absolute: bool  # G90 after this block
    motion: int  # modal motion mode after this block: 0 rapid, 1 feed
    feed: float | None  # modal feed rate after this block, units/min
    axes: tuple[float | None, ...] | None  # axis words of a motion, None when the block moves nothing
    dwell: float | None = None  # G4 seconds
    g92: tuple[float | None, ...] | None = None  # G92 axis words
    g92_clear: bool = False
    g10_l20: tuple[float | None, ...] | None = None  # G10 L20 P1 axis words: G54 so these are the position
    inches: bool = False  # G20 after this block


def words(text: str) -> list[tuple[str, float]]:
    """Split `G1X10F600` into letter/value pairs (error:1 no letter, error:2 bad number)."""
    out: list[tuple[str, float]] = []
    i = 0
    while i < len(text):
        letter = text[i]
        if not letter.isalpha():
            raise GcodeError(1)
        match = _NUMBER.match(text, i + 1)
        if match is None:
            raise GcodeError(2)
        out.append((letter, float(match.group())))
        i = match.end()
    return out


def _strip_comments(text: str) -> str:
    text = re.sub(r"\([^)]*\)", "", text)
    return text.split(";", 1)[0]


def parse_block(text: str, absolute: bool, motion: int, feed: float | None, *, jog: bool = False,
                inches: bool = False) -> Block:
    """Parse one upper-cased, whitespace-free line against the current modal state."""
    groups: dict[str, float] = {}
    values: dict[str, float] = {}
    for letter, value in words(_strip_comments(text)):
        if letter == "G":
            group = _GROUPS.get(value)
            if group is None or (jog and group not in ("distance", "units")):
                raise GcodeError(16 if jog else 20)
            if group in groups:
                raise GcodeError(21)
            groups[group] = value
        elif letter == "M":
            if jog:
                raise GcodeError(16)
            if value not in _M_CODES:
                raise GcodeError(20)
        elif letter in _VALUE_LETTERS:
            if letter in values:
                raise GcodeError(25)
            values[letter] = value
        else:
            raise GcodeError(20)
    if "F" in values and values["F"] < 0:
        raise GcodeError(4)
    absolute = groups.get("distance", 90 if absolute else 91) == 90
    inches = groups.get("units", 20 if inches else 21) == 20
    scale = MM_PER_INCH if inches else 1.0
    motion = int(groups.get("motion", motion))
    feed = values["F"] * scale if "F" in values else (None if jog else feed)
    axes = tuple(values[a] * scale if a in values else None for a in _AXIS_LETTERS)
    has_axes = any(v is not None for v in axes)
    non_modal = groups.get("non-modal")
    modal = (absolute, motion, feed)
    if non_modal == 4:
        if "P" not in values:
            raise GcodeError(28)
        if values["P"] < 0:
            raise GcodeError(4)
        return Block(*modal, None, dwell=values["P"], inches=inches)
    if non_modal == 10:
        if "L" not in values or "P" not in values:
            raise GcodeError(28)
        if values["L"] != 20 or values["P"] not in (0, 1):
            raise GcodeError(20 if values["L"] != 20 else 29)
        return Block(*modal, None, g10_l20=axes, inches=inches)
    if "L" in values:
        raise GcodeError(36)
    if non_modal == 92:
        if not has_axes:
            raise GcodeError(26)
        return Block(*modal, None, g92=axes, inches=inches)
    if non_modal == 92.1:
        return Block(*modal, None, g92_clear=True, inches=inches)
    if not has_axes:
        if jog:
            raise GcodeError(26)
        return Block(*modal, None, inches=inches)
    if (jog or motion == 1) and not feed:
        raise GcodeError(22)
    return Block(absolute, 1 if jog else motion, feed, axes, inches=inches)
