"""The stage table and the keys that let a re-run skip finished work and redo stale work.

A stage's key hashes what its output depends on: the stage's name, its code (the source of the
packages it runs), its parameters, its own inputs (capture: the manifest, scan.json and every
raw's actual bytes) and the recorded outputs of the stages it reads. Its record,
`stages/<stage>.key.json`, is written `started` before the stage runs and `done` (with the
sha256 of every output) only after the stage function returned, so it is the DONE marker: a
stage counts as finished only if the key still matches and every output still hashes to what
was recorded. Anything else is stale, and its files are removed before the stage runs again
(a stale checkpoint would otherwise be resumed on new inputs).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import station
from station.scanfolder import ScanFolder, atomic_write_json, sha256_file

StageName = Literal["process", "train", "export"]
Digest = dict[str, str]  # relative path -> sha256 of the file's bytes

# Names the scanfolder's atomic writers give their temp files: ".{name}.{random}.tmp" and
# ".{stem}.{random}.tmp{suffix}". One left behind means a writer was killed mid-write.
TEMP_FILE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")


@dataclass(frozen=True)
class StageSpec:
    name: StageName
    outputs: tuple[str, ...]  # globs (relative to the scan root) of the files this stage owns and hashes
    scratch: tuple[str, ...]  # files it owns but does not hash (working state such as checkpoints)
    reads: tuple[StageName, ...]  # earlier stages whose outputs are among its inputs
    code: tuple[str, ...]  # modules and packages under station/ whose source is its code version


STAGES: tuple[StageSpec, ...] = (
    StageSpec("process", ("images/*", "images_linear/*", "masks/*", "poses/**/*", "stages/process.json"), (),
              (), ("process", "rig_geometry.py", "scanfolder.py", "errors.py")),
    StageSpec("train", ("model/surface.pt", "model/infill.pt", "model/train_metrics.json", "stages/train.json"),
              ("model/checkpoint.pt",), ("process",), ("ngs", "scanfolder.py", "errors.py")),
    StageSpec("export", ("asset/*", "stages/export.json"), (), ("process", "train"),
              ("export", "ngs", "scanfolder.py", "errors.py")),
)
STAGE_NAMES: tuple[StageName, ...] = tuple(spec.name for spec in STAGES)


@lru_cache(maxsize=None)
def code_version(parts: tuple[str, ...]) -> str:
    """sha256 over the package version and the source of `parts`: editing a stage's code makes its work stale."""
    root = Path(station.__file__).parent
    digest = hashlib.sha256(station.__version__.encode())
    for part in parts:
        path = root / part
        for source in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            digest.update(str(source.relative_to(root)).encode() + b"\0" + source.read_bytes())
    return digest.hexdigest()


def capture_digest(scan: ScanFolder) -> Digest:
    """The process stage's own inputs: scan.json, the manifest and the bytes each raw really holds.

    The raws are hashed, not taken from the manifest: a raw corrupted after capture must change the key."""
    files = [scan.scan_json, scan.manifest_path] + [scan.resolve_inside(e.file) for e in scan.read_manifest()]
    return {str(path.relative_to(scan.root)): sha256_file(path) if path.is_file() else "missing" for path in files}


def _is_temp(path: Path) -> bool:
    return TEMP_FILE.match(path.name) is not None


def output_files(scan: ScanFolder, patterns: tuple[str, ...]) -> list[Path]:
    """The files matching `patterns`, temp files of killed writers excluded, in a stable order."""
    found = {p for pattern in patterns for p in scan.root.glob(pattern) if p.is_file() and not _is_temp(p)}
    return sorted(found)


def output_digest(scan: ScanFolder, spec: StageSpec) -> Digest:
    return {str(p.relative_to(scan.root)): sha256_file(p) for p in output_files(scan, spec.outputs)}


def stage_key(spec: StageSpec, params: dict[str, Any], inputs: dict[str, Digest]) -> str:
    """sha256 of the stage's name, code version, parameters and input digests (canonical JSON)."""
    blob = json.dumps({"stage": spec.name, "code": code_version(spec.code), "params": params, "inputs": inputs},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def scan_stage_key(scan: ScanFolder, spec: StageSpec, params: dict[str, Any], upstream: dict[str, Digest]) -> str:
    """The key of `spec` on `scan` now: its capture (process) or its upstream stages' recorded outputs."""
    inputs = {name: upstream[name] for name in spec.reads}
    if spec.name == "process":
        inputs["capture"] = capture_digest(scan)
    return stage_key(spec, params, inputs)


# Records --------------------------------------------------------------------------------------
def record_path(scan: ScanFolder, stage: StageName) -> Path:
    return scan.stages_dir / f"{stage}.key.json"


def read_record(scan: ScanFolder, stage: StageName) -> dict[str, Any] | None:
    """The stage's key record, or None when absent or unreadable (an unreadable record is stale)."""
    path = record_path(scan, stage)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return record if isinstance(record, dict) else None


def write_started(scan: ScanFolder, stage: StageName, key: str) -> None:
    atomic_write_json(record_path(scan, stage), {"stage": stage, "key": key, "state": "started"})


def write_done(scan: ScanFolder, stage: StageName, key: str, outputs: Digest, summary: dict[str, Any]) -> None:
    atomic_write_json(record_path(scan, stage),
                      {"stage": stage, "key": key, "state": "done", "outputs": outputs, "summary": summary})


def finished_record(scan: ScanFolder, spec: StageSpec, key: str) -> dict[str, Any] | None:
    """The stage's record if it finished under `key` and every output still verifies, else None."""
    record = read_record(scan, spec.name)
    if record is None or record.get("state") != "done" or record.get("key") != key:
        return None
    outputs = record.get("outputs")
    if not isinstance(outputs, dict) or not outputs:
        return None
    return record if output_digest(scan, spec) == outputs else None


def resumable(scan: ScanFolder, spec: StageSpec, key: str) -> bool:
    """True when this very key was started and never finished: its partial work (a checkpoint) may be kept."""
    record = read_record(scan, spec.name)
    return record is not None and record.get("state") == "started" and record.get("key") == key


def clean_stage(scan: ScanFolder, spec: StageSpec) -> None:
    """Remove a stale stage's outputs, scratch and DONE marker, so nothing of the old work leaks in."""
    for path in output_files(scan, spec.outputs + spec.scratch):
        path.unlink(missing_ok=True)
    scan.clear_done(spec.name)
    record_path(scan, spec.name).unlink(missing_ok=True)


def sweep_temp_files(scan: ScanFolder) -> list[str]:
    """Delete the temp files killed writers left; only call while holding the scan's lease."""
    removed = []
    for directory, _, names in os.walk(scan.root):
        for name in names:
            if TEMP_FILE.match(name):
                path = Path(directory) / name
                path.unlink(missing_ok=True)
                removed.append(str(path.relative_to(scan.root)))
    return removed
