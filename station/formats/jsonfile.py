"""JSON from untrusted files: bounded in size and nesting, UTF-8 only, fields checked by type.

`json.loads` on 100k nested brackets raises RecursionError and on a stray byte UnicodeDecodeError;
neither is an operator message, so every JSON read in the station goes through here.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from station.errors import FormatError, InputTooLargeError

MAX_JSON_BYTES = 64 * 1024 * 1024
MAX_DEPTH = 32  # our formats nest four deep at most (frames -> frame -> matrix -> row)


def _depth_ok(value: Any, limit: int) -> bool:
    """Nesting depth within `limit`, walked without recursion."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth > limit:
                return False
            children = item.values() if isinstance(item, dict) else item
            stack.extend((child, depth + 1) for child in children)
    return True


def parse_json(data: bytes | str, source: object, field: str | None = None) -> Any:
    """Decode one JSON document; any malformation is a FormatError naming `source` (and `field`)."""
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise FormatError(source, field, f"not UTF-8 text (byte {exc.start})") from exc
    try:
        value = json.loads(data)
    except RecursionError as exc:
        raise InputTooLargeError(source, field, "JSON nested too deeply") from exc
    except json.JSONDecodeError as exc:
        raise FormatError(source, field, f"not valid JSON ({exc})") from exc
    if not _depth_ok(value, MAX_DEPTH):
        raise InputTooLargeError(source, field, f"JSON nested deeper than {MAX_DEPTH} levels")
    return value


def read_json_bytes(path: Path, max_bytes: int = MAX_JSON_BYTES) -> bytes:
    """The bytes of a JSON file, refused unread when larger than `max_bytes`."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "missing")
    size = path.stat().st_size
    if size > max_bytes:
        raise InputTooLargeError(path, None, f"{size} bytes exceeds the {max_bytes}-byte limit for JSON")
    return path.read_bytes()


def read_json_object(path: Path, max_bytes: int = MAX_JSON_BYTES) -> dict[str, Any]:
    """A JSON file whose top level must be an object."""
    value = parse_json(read_json_bytes(path, max_bytes), path)
    if not isinstance(value, dict):
        raise FormatError(path, None, f"expected a JSON object at the top level, got {type(value).__name__}")
    return value


def is_number(value: Any) -> bool:
    """A JSON number: int or float, and not a bool (`true` is an int to Python)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def finite_number(value: Any, source: object, field: str, *, positive: bool = False,
                  low: float | None = None, high: float | None = None) -> float:
    """`value` as a float, refused unless a finite JSON number (in [low, high], > 0 if `positive`)."""
    if not is_number(value) or not math.isfinite(value):
        raise FormatError(source, field, f"must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise FormatError(source, field, f"must be positive, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise FormatError(source, field, f"must lie in [{low}, {high}], got {value!r}")
    return float(value)


def whole_number(value: Any, source: object, field: str, low: int, high: int) -> int:
    """An integer in [low, high]; 320.0 is accepted (JSON writers differ), 320.5 and "320" are not."""
    if not is_number(value) or not math.isfinite(value) or value != int(value):
        raise FormatError(source, field, f"must be a whole number, got {value!r}")
    if not low <= value <= high:
        raise FormatError(source, field, f"must lie in [{low}, {high}], got {value!r}")
    return int(value)


def text(value: Any, source: object, field: str, max_len: int = 4096) -> str:
    """A non-empty string without NUL bytes (paths and names)."""
    if not isinstance(value, str) or not value or "\x00" in value or len(value) > max_len:
        raise FormatError(source, field, f"must be a non-empty string, got {str(value)[:80]!r}")
    return value
