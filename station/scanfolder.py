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
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable, Literal

from station.errors import DiskFullError, ScanFolderError
from station.formats.jsonfile import read_json_object
from station.formats.manifest import read_manifest_records

FrameKind = Literal["shot", "plate"]


def fsync_dir(directory: Path) -> None:
    """Make a rename inside `directory` durable (POSIX needs the directory entry synced too)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _process_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# Read once at import, while single-threaded: os.umask can only be read by setting it.
FILE_MODE = 0o666 & ~_process_umask()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` so that `path` holds either its old content or all of `data`, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, FILE_MODE)  # mkstemp's 0600 would hide assets from the lab's group whatever its umask
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
    os.fchmod(fd, FILE_MODE)
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


def remove_tree(path: Path) -> None:
    """Remove a folder and what it holds, or only the link when `path` is a symlink (never its target)."""
    path = Path(path)
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


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
        return self._line

    @cached_property
    def _line(self) -> str:
        """Serialised once: a scan rewrites its whole manifest after every frame."""
        return json.dumps(asdict(self), sort_keys=True)


class ScanFolder:
    """Paths and safe I/O for one scan folder. Creating the object touches no disk.

    A staged view (`staged`) sends a stage's output folders to fresh hidden siblings
    (`.images.new`, ...) and holds its DONE marker back, so `commit` can swap the new result in
    whole; every other path, and every path read from a file, means what it will mean after the swap.
    """

    def __init__(self, root: Path | str):
        self.root = Path(root).resolve()
        self._staging: dict[str, Path] = {}  # output folder name -> its fresh sibling
        self._held: dict[str, dict[str, Any]] = {}  # DONE markers held back until the commit

    def _folder(self, name: str) -> Path:
        return self._staging.get(name, self.root / name)

    # Paths owned by each stage -------------------------------------------------------------
    scan_json = property(lambda self: self.root / "scan.json")
    manifest_path = property(lambda self: self.root / "manifest.jsonl")
    raw_dir = property(lambda self: self.root / "raw")
    sim_truth_dir = property(lambda self: self.root / "sim_truth")
    images_dir = property(lambda self: self._folder("images"))
    images_linear_dir = property(lambda self: self._folder("images_linear"))
    masks_dir = property(lambda self: self._folder("masks"))
    poses_dir = property(lambda self: self._folder("poses"))
    transforms_path = property(lambda self: self._folder("poses") / "transforms.json")
    model_dir = property(lambda self: self._folder("model"))
    asset_dir = property(lambda self: self._folder("asset"))
    stages_dir = property(lambda self: self.root / "stages")

    def resolve_inside(self, relative: str | Path) -> Path:
        """Resolve a path named by a file in this folder; refuse anything that escapes it."""
        candidate = (self.root / relative).resolve()
        if candidate != self.root and self.root not in candidate.parents:
            raise ScanFolderError(f"{self.root}: path {str(relative)!r} resolves outside the scan folder")
        parts = candidate.relative_to(self.root).parts
        if parts and parts[0] in self._staging:
            return self._staging[parts[0]].joinpath(*parts[1:])
        return candidate

    # Stage output folders: containment and the atomic swap --------------------------------------
    def owned_folder(self, name: str) -> Path:
        """`root/name`, refused when it is a symlink or not a plain child of the root: a stage never
        writes, nor deletes, through a link."""
        path = self.root / name
        if path.is_symlink():
            raise ScanFolderError(f"{path}: is a symbolic link; a stage folder must be a real folder inside "
                                  "the scan folder (nothing is written or deleted through a link)")
        if path.exists() and not path.is_dir():
            raise ScanFolderError(f"{path}: expected a folder, found a file")
        if path.resolve().parent != self.root:
            raise ScanFolderError(f"{self.root}: stage folder {name!r} resolves outside the scan folder")
        return path

    def staging_path(self, name: str) -> Path:
        return self.root / f".{name}.new"

    def _old_path(self, name: str) -> Path:
        return self.root / f".{name}.old"

    def _journal(self, stage: str) -> Path:
        return self.stages_dir / f".{stage}.swap.json"

    def staged(self, stage: str, folders: Iterable[str], keep: bool = False) -> "ScanFolder":
        """A view of this folder whose `folders` are fresh siblings; `keep` reuses a sibling left by an
        interrupted run of the same work (a resumable checkpoint)."""
        self.recover(stage, folders)
        view = ScanFolder(self.root)
        for name in folders:
            self.owned_folder(name)
            self.owned_folder(f".{name}.new")
            staging = self.staging_path(name)
            if not keep:
                remove_tree(staging)
            staging.mkdir(exist_ok=True)
            view._staging[name] = staging
        self.owned_folder("stages").mkdir(exist_ok=True)
        return view

    def commit(self, staged: "ScanFolder", stage: str) -> None:
        """Swap the staged folders in (a journal makes a crash half-way roll forward), then write the
        held DONE markers."""
        names = list(staged._staging)
        atomic_write_json(self._journal(stage), {"folders": names})
        self._roll_forward(stage, names)
        for held_stage, info in staged._held.items():
            self.mark_done(held_stage, info)

    def recover(self, stage: str, folders: Iterable[str]) -> None:
        """Finish a swap a crash interrupted, and drop the old folders a finished swap left behind."""
        self.owned_folder("stages")
        journal = self._journal(stage)
        if journal.is_file():
            names = self.read_json(journal).get("folders", [])
            self._roll_forward(stage, [n for n in names if isinstance(n, str) and n in set(folders)])
        for name in folders:
            remove_tree(self._old_path(name))

    def _roll_forward(self, stage: str, names: list[str]) -> None:
        for name in names:
            target, staging, old = self.owned_folder(name), self.staging_path(name), self._old_path(name)
            if staging.is_dir() and not staging.is_symlink():
                if target.exists():
                    remove_tree(old)
                    os.replace(target, old)
                os.replace(staging, target)
        fsync_dir(self.root)
        self._journal(stage).unlink(missing_ok=True)
        for name in names:
            remove_tree(self._old_path(name))

    # scan.json -----------------------------------------------------------------------------
    def read_scan_json(self) -> dict[str, Any]:
        return self.read_json(self.scan_json)

    def read_json(self, path: Path) -> dict[str, Any]:
        return read_json_object(path)

    # manifest.jsonl -----------------------------------------------------------------------
    def read_manifest(self) -> list[ManifestEntry]:
        if not self.manifest_path.exists():
            return []
        entries = [ManifestEntry(**record) for record in read_manifest_records(self.manifest_path)]
        for entry in entries:
            self.resolve_inside(entry.file)
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
        """Write stages/<stage>.json; a staged view holds it back until its folders are swapped in."""
        if self._staging:
            self._held[stage] = info
        else:
            atomic_write_json(self.owned_folder("stages") / f"{stage}.json", info)

    def stage_info(self, stage: str) -> dict[str, Any] | None:
        path = self.stages_dir / f"{stage}.json"
        return self.read_json(path) if path.exists() else None

    def is_done(self, stage: str) -> bool:
        return (self.stages_dir / f"{stage}.json").exists()

    def clear_done(self, stage: str) -> None:
        (self.owned_folder("stages") / f"{stage}.json").unlink(missing_ok=True)
