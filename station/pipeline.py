"""The one stage table: what each stage reads and writes, how it runs, and when it counts as done.

The CLI, the batch runner and the dashboard all walk this table. A stage's key hashes what its
output depends on: its name, its code (the source of the packages it runs), its parameters, its
own inputs (process: scan.json, the manifest and every raw's bytes) and the outputs of the
stages it reads. Its record, `stages/<stage>.key.json`, is written `started` before the stage
runs and `done` (with the sha256 of every output) only after its folders were swapped in, so it
is the one DONE marker: a stage is finished only while the key still matches and every output
still hashes to what was recorded. Anything else is stale and runs again into fresh folders.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Literal

import station
from station.errors import ScanFolderError
from station.scanfolder import ScanFolder, atomic_write_json, remove_tree, sha256_file

StageName = Literal["process", "train", "export"]
Digest = dict[str, str]  # relative path -> sha256 of the file's bytes
Progress = Callable[[int, int, str], None]
RunFunction = Callable[[ScanFolder, ScanFolder, dict[str, Any], "Progress | None"], tuple[Any, dict[str, Any]]]

# Names the scanfolder's atomic writers give their temp files: ".{name}.{random}.tmp" and
# ".{stem}.{random}.tmp{suffix}". One left behind means a writer was killed mid-write.
TEMP_FILE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")


@dataclass(frozen=True)
class StageSpec:
    name: StageName
    folders: tuple[str, ...]  # output folders, written fresh beside the old ones and swapped in whole
    outputs: tuple[str, ...]  # globs (relative to the scan root) of the files this stage owns and hashes
    scratch: tuple[str, ...]  # files it owns but does not hash (working state such as checkpoints)
    reads: tuple[StageName, ...]  # earlier stages whose outputs are among its inputs
    code: tuple[str, ...]  # modules and packages under station/ whose source is its code version
    run: RunFunction  # (scan, staged view, params, progress) -> (full result, small JSON summary)


def _process(scan: ScanFolder, staged: ScanFolder, params: dict[str, Any], progress: Progress | None):
    from station.process.develop_stage import ProcessSettings
    from station.process.stage import process_scan

    rig_model = Path(params["rig_model"]) if params.get("rig_model") else None
    result = process_scan(staged, ProcessSettings(training_width=params.get("training_width")), rig_model=rig_model)
    summary = {"flags": result["flags"], "usable_shots": result["develop"]["usable_shots"],
               "frames": [{"file": f["file"], "flags": f["flags"]} for f in result["develop"]["frames"] if f["flags"]]}
    return result, summary


def _train(scan: ScanFolder, staged: ScanFolder, params: dict[str, Any], progress: Progress | None):
    from station.ngs.pipeline import train_scan
    from station.ngs.presets import make_config

    method, preset = params.get("method", "ngs"), params.get("preset", "fast")
    total = make_config(method, preset).steps
    report = train_scan(staged, method=method, preset=preset, inputs=inputs_fingerprint(scan, spec("train")),
                        progress=(lambda step, terms: progress(step, total, f"loss {terms['loss']:.4f}"))
                        if progress else None)
    return report, {**asdict(report), "preset": preset}


def _export(scan: ScanFolder, staged: ScanFolder, params: dict[str, Any], progress: Progress | None):
    from station.export.stage import ExportConfig, export_scan

    reference = params.get("reference_mesh")
    report = export_scan(staged, ExportConfig(stl=bool(params.get("stl", False)),
                                              reference_mesh=Path(reference) if reference else None))
    report.files = {name: scan.asset_dir / path.name for name, path in report.files.items()}
    # each check's reason is "<measurement>: <advice>"; the measurement is enough for the summary
    failed = [check.reason.split(": ")[0] for check in report.gate.failures()]
    return report, {"pass": report.passed, "failed_checks": failed}


STAGES: tuple[StageSpec, ...] = (
    StageSpec("process", ("images", "images_linear", "masks", "poses"),
              ("images/*", "images_linear/*", "masks/*", "poses/**/*", "stages/process.json"), (),
              (), ("process", "rig_geometry.py", "scanfolder.py", "errors.py"), _process),
    StageSpec("train", ("model",),
              ("model/surface.pt", "model/infill.pt", "model/train_metrics.json", "stages/train.json"),
              ("model/checkpoint.pt",), ("process",), ("ngs", "scanfolder.py", "errors.py"), _train),
    StageSpec("export", ("asset",), ("asset/*", "stages/export.json"), (), ("process", "train"),
              ("export", "ngs", "scanfolder.py", "errors.py"), _export),
)
STAGE_NAMES: tuple[StageName, ...] = tuple(s.name for s in STAGES)
VERDICT = ("asset/gate.json", "stages/export.json")  # what export removes first


def spec(name: str) -> StageSpec:
    return next(s for s in STAGES if s.name == name)


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


def _inside_without_links(scan: ScanFolder, path: Path) -> bool:
    """True when no folder between the scan root and `path` (nor `path`) is a symlink."""
    current = path
    while current != scan.root:
        if current.is_symlink():
            return False
        current = current.parent
    return True


def output_files(scan: ScanFolder, patterns: tuple[str, ...]) -> list[Path]:
    """The files matching `patterns`, reached without a symlink, temp files of killed writers excluded."""
    found = {p for pattern in patterns for p in scan.root.glob(pattern)
             if p.is_file() and TEMP_FILE.match(p.name) is None and _inside_without_links(scan, p)}
    return sorted(found)


def output_digest(scan: ScanFolder, stage: StageSpec) -> Digest:
    return {str(p.relative_to(scan.root)): sha256_file(p) for p in output_files(scan, stage.outputs)}


def inputs_fingerprint(scan: ScanFolder, stage: StageSpec) -> str:
    """sha256 of the current outputs of the stages `stage` reads: what a resumed checkpoint must match."""
    blob = json.dumps({name: output_digest(scan, spec(name)) for name in stage.reads}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def stage_key(stage: StageSpec, params: dict[str, Any], inputs: dict[str, Digest]) -> str:
    """sha256 of the stage's name, code version, parameters and input digests (canonical JSON)."""
    blob = json.dumps({"stage": stage.name, "code": code_version(stage.code), "params": params, "inputs": inputs},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def scan_stage_key(scan: ScanFolder, stage: StageSpec, params: dict[str, Any], upstream: dict[str, Digest]) -> str:
    """The key of `stage` on `scan` now: its capture (process) or its upstream stages' recorded outputs."""
    inputs = {name: upstream[name] for name in stage.reads}
    if stage.name == "process":
        inputs["capture"] = capture_digest(scan)
    return stage_key(stage, params, inputs)


# Records --------------------------------------------------------------------------------------
def record_path(scan: ScanFolder, stage: StageName) -> Path:
    return scan.owned_folder("stages") / f"{stage}.key.json"


def read_record(scan: ScanFolder, stage: StageName) -> dict[str, Any] | None:
    """The stage's key record, or None when absent or unreadable (an unreadable record is stale)."""
    path = record_path(scan, stage)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        return None
    return record if isinstance(record, dict) else None


def write_started(scan: ScanFolder, stage: StageName, key: str) -> None:
    atomic_write_json(record_path(scan, stage), {"stage": stage, "key": key, "state": "started"})


def write_done(scan: ScanFolder, stage: StageName, key: str, outputs: Digest, summary: dict[str, Any]) -> None:
    atomic_write_json(record_path(scan, stage),
                      {"stage": stage, "key": key, "state": "done", "outputs": outputs, "summary": summary})


def finished_record(scan: ScanFolder, stage: StageSpec, key: str) -> dict[str, Any] | None:
    """The stage's record if it finished under `key` and every output still verifies, else None."""
    record = read_record(scan, stage.name)
    if record is None or record.get("state") != "done" or record.get("key") != key:
        return None
    outputs = record.get("outputs")
    if not isinstance(outputs, dict) or not outputs:
        return None
    return record if output_digest(scan, stage) == outputs else None


def resumable(scan: ScanFolder, stage: StageSpec, key: str) -> bool:
    """True when this very key was started and never finished: its partial work (a checkpoint) may be kept."""
    record = read_record(scan, stage.name)
    return record is not None and record.get("state") == "started" and record.get("key") == key


def clean_stage(scan: ScanFolder, stage: StageSpec) -> None:
    """Forget a stale stage: its half-written fresh folders, scratch, DONE marker and record. Its last
    complete outputs stay until a new run swaps its own in; nothing is removed through a link."""
    for name in stage.folders:
        remove_tree(scan.staging_path(name))
    for path in output_files(scan, stage.scratch):
        path.unlink(missing_ok=True)
    scan.clear_done(stage.name)
    record_path(scan, stage.name).unlink(missing_ok=True)


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


# Running ----------------------------------------------------------------------------------------
def recover(scan: ScanFolder) -> None:
    """Finish every swap a crash cut short, so no stage reads (or hashes) a half-swapped folder."""
    if not scan.root.is_dir():
        raise ScanFolderError(f"{scan.root}: scan folder not found")
    for stage in STAGES:
        scan.recover(stage.name, stage.folders)


def perform(scan_root: Path | str, name: str, params: dict[str, Any],
            progress: Progress | None = None) -> tuple[Any, dict[str, Any]]:
    """Run one stage into fresh folders and swap them in: the scan keeps its old complete result or
    gets the whole new one. The caller keeps the record (the batch runner, or `run_stage`)."""
    scan, stage = ScanFolder(scan_root), spec(name)
    recover(scan)
    if name == "export":  # a failed export must never sit under an earlier pass
        for relative in VERDICT:
            path = scan.root / relative
            if _inside_without_links(scan, path) and path.is_file():
                path.unlink()
    keep = bool(stage.scratch)  # a stage with working state may resume from its fresh folders
    staged = scan.staged(name, stage.folders, keep=keep)
    try:
        result, summary = stage.run(scan, staged, params, progress)
    except BaseException:
        if not keep:
            for folder in stage.folders:
                remove_tree(scan.staging_path(folder))
        raise
    scan.commit(staged, name)
    return result, summary


def run_stage(scan_root: Path | str, name: str, params: dict[str, Any], progress: Progress | None = None,
              skip_done: bool = False) -> Any | None:
    """One stage as the CLI runs it, with the batch's records: skipped (None) when `skip_done` and it
    finished under the same key; resumed only from partial work of that very key."""
    scan, stage = ScanFolder(scan_root), spec(name)
    recover(scan)
    upstream = {read: output_digest(scan, spec(read)) for read in stage.reads}
    key = scan_stage_key(scan, stage, params, upstream)
    if skip_done and finished_record(scan, stage, key) is not None:
        return None
    if not resumable(scan, stage, key):
        clean_stage(scan, stage)
    write_started(scan, name, key)
    result, summary = perform(scan.root, name, params, progress)
    write_done(scan, name, key, output_digest(scan, stage), summary)
    return result


def run_pipeline(scan_root: Path | str, params: dict[str, dict[str, Any]], progress: Progress | None = None,
                 say: Callable[[str], None] = lambda text: None) -> Any:
    """Walk the table on one scan: a stage finished under the same key is skipped, the last (export,
    whose verdict the caller prints) always runs. Returns the last stage's result."""
    result = None
    for stage in STAGES:
        say(f"{stage.name} ...")
        last = stage is STAGES[-1]
        started = time.monotonic()
        result = run_stage(scan_root, stage.name, params.get(stage.name, {}), progress, skip_done=not last)
        say(f"{stage.name}: finished earlier; its outputs verify" if result is None
            else f"{stage.name}: {time.monotonic() - started:.0f} s{_inner_times(result)}")
    return result


def _inner_times(result: Any) -> str:
    """The process stage's own steps, which take time of their own: develop, poses, masks across rings."""
    if not isinstance(result, dict) or "develop" not in result:
        return ""
    steps = {"develop": result["develop"].get("seconds"), "poses": result.get("poses", {}).get("seconds"),
             "masks across rings": result.get("masks_across_rings", {}).get("seconds")}
    return " (" + ", ".join(f"{name} {s:.0f} s" for name, s in steps.items() if isinstance(s, (int, float))) + ")"


def stage_done(scan: ScanFolder, name: str) -> bool:
    """Whether the dashboard shows `name` done: capture's marker, or a stage's done record whose
    outputs are all present (the runner and the CLI also re-hash them against the key)."""
    if name == "capture":
        return scan.is_done("capture")
    try:
        record = read_record(scan, name)
    except ScanFolderError:  # a linked stages/ folder: nothing in it counts
        return False
    outputs = record.get("outputs") if record and record.get("state") == "done" else None
    return isinstance(outputs, dict) and bool(outputs) and all(_present(scan, path) for path in outputs)


def _present(scan: ScanFolder, relative: object) -> bool:
    try:
        return isinstance(relative, str) and scan.resolve_inside(relative).is_file()
    except ScanFolderError:
        return False
