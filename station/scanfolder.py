"""The scan-folder contract: where each stage's files live, and how they are written.

Every stage talks to the next only through a scan folder (see docs/contract in shared/).
This module owns the paths, the crash-safe write (temp file, fsync, rename, fsync of the
directory), the manifest of captured frames, and stage-completion markers. A scan folder may
come from anywhere, so every relative path read from its files is resolved and refused if it
escapes the folder.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal

from station.errors import DiskFullError, ScanFolderError

FrameKind = Literal["shot", "plate"]


def fsync_dir(directory: Path) -> None:
    """Make a rename inside `directory` durable (POSIX needs the directory entry synced too)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` so that `path` holds either its old content or all of `data`, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def atomic_write_with(path: Path, writer) -> None:
    """Atomic write for libraries that want a filename: `writer(tmp_path)` writes, we rename.

    The temp name keeps the final suffix so format-sniffing writers (PNG, EXR, PLY) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        writer(Path(tmp))
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def require_free_space(directory: Path, needed_bytes: int, what: str) -> None:
    """Refuse to start work that would fill the disk half-way through."""
    directory = Path(directory)
    probe = directory if directory.exists() else next(p for p in directory.parents if p.exists())
    free = shutil.disk_usage(probe).free
    if free < needed_bytes:
        raise DiskFullError(
            f"{what}: needs {needed_bytes / 1e6:.1f} MB free in {probe}, only {free / 1e6:.1f} MB left"
        )


@dataclass(frozen=True)
class ManifestEntry:
    """One captured frame, as one line of manifest.jsonl."""

    file: str
    sha256: str
    elevation_deg: float
    azimuth_deg: float
    kind: FrameKind
    exposure_s: float
    iso: int
    utc: str
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @staticmethod
    def from_json(line: str, source: Path) -> "ManifestEntry":
        try:
            raw = json.loads(line)
            return ManifestEntry(
                file=str(raw["file"]),
                sha256=str(raw["sha256"]),
                elevation_deg=float(raw["elevation_deg"]),
                azimuth_deg=float(raw["azimuth_deg"]),
                kind=raw["kind"],
                exposure_s=float(raw.get("exposure_s", 0.0)),
                iso=int(raw.get("iso", 0)),
                utc=str(raw.get("utc", "")),
                extra=dict(raw.get("extra", {})),
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise ScanFolderError(f"{source}: malformed manifest line ({exc}): {line[:120]!r}") from exc


class ScanFolder:
    """Paths and safe I/O for one scan folder. Creating the object touches no disk."""

    def __init__(self, root: Path | str):
        self.root = Path(root).resolve()

    # Paths owned by each stage -------------------------------------------------------------
    scan_json = property(lambda self: self.root / "scan.json")
    manifest_path = property(lambda self: self.root / "manifest.jsonl")
    raw_dir = property(lambda self: self.root / "raw")
    sim_truth_dir = property(lambda self: self.root / "sim_truth")
    images_dir = property(lambda self: self.root / "images")
    images_linear_dir = property(lambda self: self.root / "images_linear")
    masks_dir = property(lambda self: self.root / "masks")
    poses_dir = property(lambda self: self.root / "poses")
    transforms_path = property(lambda self: self.root / "poses" / "transforms.json")
    model_dir = property(lambda self: self.root / "model")
    asset_dir = property(lambda self: self.root / "asset")
    stages_dir = property(lambda self: self.root / "stages")

    def resolve_inside(self, relative: str | Path) -> Path:
        """Resolve a path named by a file in this folder; refuse anything that escapes it."""
        candidate = (self.root / relative).resolve()
        if candidate != self.root and self.root not in candidate.parents:
            raise ScanFolderError(f"{self.root}: path {str(relative)!r} resolves outside the scan folder")
        return candidate

    # scan.json -----------------------------------------------------------------------------
    def read_scan_json(self) -> dict[str, Any]:
        return self.read_json(self.scan_json)

    def read_json(self, path: Path) -> dict[str, Any]:
        if not path.is_file():
            raise ScanFolderError(f"{path}: missing")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ScanFolderError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(data, dict):
            raise ScanFolderError(f"{path}: expected a JSON object at the top level")
        return data

    # manifest.jsonl -----------------------------------------------------------------------
    def read_manifest(self) -> list[ManifestEntry]:
        if not self.manifest_path.exists():
            return []
        entries = []
        for line in self.manifest_path.read_text(encoding="utf-8").splitlines():
            if line.strip():
                entry = ManifestEntry.from_json(line, self.manifest_path)
                self.resolve_inside(entry.file)
                entries.append(entry)
        return entries

    def write_manifest(self, entries: Iterable[ManifestEntry]) -> None:
        """Rewrite the whole manifest atomically: a kill can never leave half a line."""
        text = "".join(entry.to_json() + "\n" for entry in entries)
        atomic_write_text(self.manifest_path, text)

    def verify_entry(self, entry: ManifestEntry) -> bool:
        """True if the frame's file exists and its bytes match the recorded checksum."""
        path = self.resolve_inside(entry.file)
        return path.is_file() and sha256_file(path) == entry.sha256

    # Stage markers ------------------------------------------------------------------------
    def mark_done(self, stage: str, info: dict[str, Any]) -> None:
        atomic_write_json(self.stages_dir / f"{stage}.json", info)

    def stage_info(self, stage: str) -> dict[str, Any] | None:
        path = self.stages_dir / f"{stage}.json"
        return self.read_json(path) if path.exists() else None

    def is_done(self, stage: str) -> bool:
        return (self.stages_dir / f"{stage}.json").exists()

    def clear_done(self, stage: str) -> None:
        (self.stages_dir / f"{stage}.json").unlink(missing_ok=True)
