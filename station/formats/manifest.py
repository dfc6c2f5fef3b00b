"""manifest.jsonl, one captured frame a line: each line checked by field before the scan uses it.

A NaN or out-of-range elevation would match no plate ring (every comparison with NaN is false) and
silently pick the wrong plate, so angles must be finite and within the hemisphere.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from station.errors import FormatError
from station.formats.jsonfile import finite_number, parse_json, read_json_bytes, text, whole_number

MAX_MANIFEST_BYTES = 16 * 1024 * 1024
KINDS = ("shot", "plate")
SHA256 = re.compile(r"[0-9a-f]{64}")


def manifest_record(line: str, source: object, number: int) -> dict[str, Any]:
    """One line -> the ManifestEntry fields, every one checked; `number` is the 1-based line number."""
    where = f"line {number}"
    raw = parse_json(line, source, where)
    if not isinstance(raw, dict):
        raise FormatError(source, where, "must be a JSON object")
    sha = text(raw.get("sha256"), source, f"{where}.sha256", max_len=64)
    if not SHA256.fullmatch(sha):
        raise FormatError(source, f"{where}.sha256", "must be 64 lower-case hex digits")
    if raw.get("kind") not in KINDS:
        raise FormatError(source, f"{where}.kind", f"must be one of {KINDS}, got {str(raw.get('kind'))[:40]!r}")
    extra = raw.get("extra", {})
    if not isinstance(extra, dict):
        raise FormatError(source, f"{where}.extra", "must be an object")
    utc = raw.get("utc", "")
    if not isinstance(utc, str):
        raise FormatError(source, f"{where}.utc", "must be a string")
    file = text(raw.get("file"), source, f"{where}.file")
    if file.startswith("/") or ".." in file.replace("\\", "/").split("/"):
        raise FormatError(source, f"{where}.file", f"{file[:80]!r} must be a path inside the scan folder")
    return {
        "file": file,
        "sha256": sha,
        "elevation_deg": finite_number(raw.get("elevation_deg"), source, f"{where}.elevation_deg", low=-90.0, high=90.0),
        "azimuth_deg": finite_number(raw.get("azimuth_deg"), source, f"{where}.azimuth_deg", low=-360.0, high=720.0),
        "kind": raw["kind"],
        "exposure_s": finite_number(raw.get("exposure_s", 0.0), source, f"{where}.exposure_s", low=0.0, high=3600.0),
        "iso": whole_number(raw.get("iso", 0), source, f"{where}.iso", 0, 10_000_000),
        "utc": utc,
        "extra": extra,
    }


def read_manifest_records(path: Path) -> list[dict[str, Any]]:
    """Every non-blank line of manifest.jsonl as checked fields; non-UTF-8 bytes are named by line."""
    records = []
    for number, line in enumerate(read_json_bytes(path, MAX_MANIFEST_BYTES).split(b"\n"), start=1):
        if line.strip():
            try:
                decoded = line.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise FormatError(path, f"line {number}", f"not UTF-8 text (byte {exc.start})") from exc
            records.append(manifest_record(decoded, path, number))
    return records
