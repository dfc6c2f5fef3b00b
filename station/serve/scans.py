"""The scans the dashboard may show: the overnight queue's and its own, with stages, verdicts and reports.

Only those scans are reachable, each under an opaque key rather than its path, so a URL can never
name another folder; and a report is served only if it resolves inside its scan folder (a scan
folder may come from anywhere, and a symlinked report could point at any file on the station).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable

from station.batch.store import Job, JobStore
from station.errors import BadInputError, ScanFolderError
from station.pipeline import STAGE_NAMES, stage_done
from station.scanfolder import ScanFolder

STAGES = ("capture", *STAGE_NAMES)  # capture is the session's (stages/capture.json); the rest the pipeline's
REPORT = "asset/report.html"
GATE = "asset/gate.json"
MAX_GATE_BYTES = 1 << 20


class UnknownScanError(BadInputError):
    """No scan of the queue or of this dashboard has that key, or it has no report yet."""


def scan_key(folder: Path | str) -> str:
    """The URL name of a scan folder: a digest of its resolved path."""
    return hashlib.sha256(str(Path(folder).resolve()).encode("utf-8")).hexdigest()[:16]


class ScanCatalog:
    """Reads the queue and the dashboard's own scans; never writes.

    The queue file is opened once it exists (`station batch add` creates it, perhaps after the
    dashboard started); the dashboard never creates an empty one.
    """

    def __init__(self, queue: Path | None, dashboard_folders: Callable[[], list[Path]]):
        self.queue = queue
        self.dashboard_folders = dashboard_folders
        self._store: JobStore | None = None

    def queue_exists(self) -> bool:
        return self.queue is not None and self.queue.is_file()

    def rows(self) -> list[dict]:
        """One row per scan, queue first: job state and stage, stage markers, gate verdict, report link."""
        jobs = self._jobs()
        queued = {Path(job.scan).resolve() for job in jobs}
        rows = [self._row(Path(job.scan), "queue", job) for job in jobs]
        rows += [self._row(folder, "dashboard", None) for folder in self.dashboard_folders() if folder.resolve() not in queued]
        return rows

    def report(self, key: str) -> Path:
        """The report of the scan with this key; refused unless it is a file inside that scan folder."""
        folder = self._known().get(key)
        if folder is None:
            raise UnknownScanError(f"no scan in the queue or from this dashboard has the key {key!r}")
        path = ScanFolder(folder).resolve_inside(REPORT)
        if not path.is_file():
            raise UnknownScanError(f"{folder}: no {REPORT} yet (the export stage writes it)")
        return path

    def _jobs(self) -> list[Job]:
        if self._store is None and self.queue_exists():
            self._store = JobStore(self.queue)
        return self._store.jobs() if self._store is not None else []

    def _known(self) -> dict[str, Path]:
        folders = [Path(job.scan) for job in self._jobs()]
        return {scan_key(folder): folder for folder in folders + self.dashboard_folders()}

    def _row(self, folder: Path, source: str, job: Job | None) -> dict:
        scan = ScanFolder(folder)
        key = scan_key(folder)
        return {
            "key": key,
            "name": scan.root.name,
            "folder": str(scan.root),
            "source": source,
            "job": None if job is None else {k: v for k, v in job.to_dict().items() if k not in ("scan", "lease_owner")},
            "stages": {stage: stage_done(scan, stage) for stage in STAGES},
            "gate": gate_verdict(scan),
            "report_url": f"/scans/{key}/report" if _has_report(scan) else None,
        }


def _has_report(scan: ScanFolder) -> bool:
    try:
        return scan.resolve_inside(REPORT).is_file()
    except ScanFolderError:
        return False


def gate_verdict(scan: ScanFolder) -> dict | None:
    """asset/gate.json boiled down to pass and the failed checks' reasons; None before export."""
    path = scan.root / GATE
    if not path.exists():
        return None
    try:
        inside = scan.resolve_inside(GATE)
        if inside.stat().st_size > MAX_GATE_BYTES:
            raise ScanFolderError(f"{inside}: larger than {MAX_GATE_BYTES} bytes, not a gate verdict")
        data = scan.read_json(inside)
    except (ScanFolderError, OSError) as exc:
        return {"pass": None, "failed": [], "error": str(exc)}
    passed, checks = data.get("pass"), data.get("checks", [])
    if not isinstance(passed, bool) or not isinstance(checks, list):
        return {"pass": None, "failed": [], "error": f"{path}: malformed (expected 'pass' true/false and a 'checks' list)"}
    failed = [str(c.get("reason") or c.get("name")) for c in checks if isinstance(c, dict) and c.get("pass") is False]
    return {"pass": passed, "failed": failed}
