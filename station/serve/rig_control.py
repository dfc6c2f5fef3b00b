"""The dashboard's scan runner: one scan at a time on a background thread, and what it last saw.

Web handlers never touch the devices. They read a snapshot of the runner's state, and flip the
session's ScanControl, which the session honours between frames with the turntable at rest. The
devices are opened for each scan and closed after it, by the same functions `station scan` uses
(station/cli_scan.py), so the serial port and the camera are free between scans.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Literal

from station.capture.session import OperatorAction, ScanCancelledError, ScanControl, ScanSummary
from station.errors import BadInputError, StationError

log = logging.getLogger(__name__)

Phase = Literal["connecting", "scanning", "cancelling", "finished", "cancelled", "failed"]
_RUNNING: tuple[Phase, ...] = ("connecting", "scanning", "cancelling")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
_STONE = re.compile(r"(?:[a-z]+:)?[0-9]{1,9}")  # a simulated stone's seed or look:seed, never a file path
MAX_ELEVATIONS, MAX_AZIMUTHS = 12, 360


class RunnerStateError(BadInputError):
    """The action does not fit what the rig is doing (start while scanning, resume when not paused)."""


@dataclass(frozen=True)
class ScanRequest:
    """What the operator asked for; `name` is the folder created under the dashboard's output folder."""

    name: str
    elevations: int
    azimuths: int
    stone: str | None = None

    def __post_init__(self) -> None:
        if not _NAME.fullmatch(self.name):
            raise BadInputError(f"scan name {self.name!r}: use 1-64 letters, digits, '.', '_' or '-', not starting with a dot")
        if not 1 <= self.elevations <= MAX_ELEVATIONS:
            raise BadInputError(f"elevations {self.elevations}: expected 1 to {MAX_ELEVATIONS}")
        if not 1 <= self.azimuths <= MAX_AZIMUTHS:
            raise BadInputError(f"azimuths {self.azimuths}: expected 1 to {MAX_AZIMUTHS}")
        if self.stone is not None and not _STONE.fullmatch(self.stone):
            raise BadInputError(f"stone {self.stone!r}: expected a seed such as 7 or look:seed such as pale:3")


class DashboardOperator:
    """The session's Operator for hardware scans: shows its request on the page, waits for Done."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self.prompt: str | None = None
        self._answered = False
        self._cancelled = False

    def request(self, action: OperatorAction, message: str) -> None:
        with self._changed:
            self.prompt, self._answered = message, False
            while not (self._answered or self._cancelled):
                self._changed.wait()
            self.prompt = None
            if self._cancelled:
                raise ScanCancelledError(f"scan cancelled by the operator while asked: {message}")

    def confirm(self) -> None:
        with self._changed:
            if self.prompt is None:
                raise RunnerStateError("nothing is waiting for the operator")
            self._answered = True
            self._changed.notify_all()

    def cancel(self) -> None:
        with self._changed:
            self._cancelled = True
            self._changed.notify_all()


@dataclass
class ScanHooks:
    """What the dashboard hands to a scan function so it can follow and steer the session."""

    control: ScanControl
    operator: DashboardOperator
    progress: Callable[[int, int, str], None]


ScanFunction = Callable[[Path, ScanRequest, ScanHooks], ScanSummary]


@dataclass
class _Scan:
    """The runner's record of one scan (guarded by the runner's lock)."""

    request: ScanRequest
    folder: Path
    control: ScanControl = field(default_factory=ScanControl)
    operator: DashboardOperator = field(default_factory=DashboardOperator)
    phase: Phase = "connecting"
    done: int = 0
    total: int = 0
    latest: str | None = None  # newest stored raw, relative to the folder
    message: str = ""
    started: float = field(default_factory=time.monotonic)
    ended: float | None = None
    summary: ScanSummary | None = None


class ScanRunner:
    """Runs the operator's scans one at a time; safe to call from any web handler thread."""

    def __init__(self, scan: ScanFunction | None, out_dir: Path, rig_label: str):
        """`scan` None: no rig is attached, and the dashboard only shows the queue."""
        self._scan_function = scan
        self.out_dir = Path(out_dir).resolve()
        self.rig_label = rig_label
        self._lock = threading.Lock()
        self._current: _Scan | None = None
        self._thread: threading.Thread | None = None
        self._folders: dict[Path, None] = {}  # every folder scanned into, in order

    # -- operator actions ------------------------------------------------------------------
    def start(self, request: ScanRequest) -> None:
        """Start (or, for a folder that holds part of the same scan, resume) a scan in the background."""
        scan_function = self._scan_function
        if scan_function is None:
            raise RunnerStateError(f"cannot scan: {self.rig_label}")
        with self._lock:
            if self._current is not None and self._current.phase in _RUNNING:
                raise RunnerStateError(f"scan {self._current.request.name} is still running; wait, or cancel it first")
            scan = _Scan(request, self.out_dir / request.name)
            self._current = scan
            self._folders[scan.folder] = None
            self._thread = threading.Thread(
                target=self._run, args=(scan_function, scan), name=f"scan {request.name}", daemon=True
            )
            self._thread.start()

    def pause(self) -> None:
        self._running("pause").control.pause()

    def resume(self) -> None:
        scan = self._running("resume")
        if not scan.control.paused:
            raise RunnerStateError(f"scan {scan.request.name} is not paused")
        scan.control.resume()

    def cancel(self) -> None:
        """Stop at the next frame boundary; the frames shot so far stay, so starting it again resumes."""
        with self._lock:
            scan = self._running_locked("cancel")
            scan.phase = "cancelling"
        scan.control.cancel()
        scan.operator.cancel()

    def confirm_operator(self) -> None:
        self._running("confirm").operator.confirm()

    def _running(self, action: str) -> _Scan:
        with self._lock:
            return self._running_locked(action)

    def _running_locked(self, action: str) -> _Scan:
        scan = self._current
        if scan is None or scan.phase not in ("connecting", "scanning"):
            raise RunnerStateError(f"cannot {action}: no scan is running")
        return scan

    def wait(self, timeout: float) -> None:
        """Give the scan thread up to `timeout` seconds to end (at shutdown, after a cancel)."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout)

    # -- what the page shows ---------------------------------------------------------------
    def folders(self) -> list[Path]:
        with self._lock:
            return list(self._folders)

    def latest_frame(self) -> tuple[Path, str] | None:
        """(scan folder, newest raw in it) of the current or last scan, if a frame was stored."""
        with self._lock:
            scan = self._current
            return None if scan is None or scan.latest is None else (scan.folder, scan.latest)

    def snapshot(self) -> dict:
        with self._lock:
            scan = self._current
            if scan is None:
                return {"rig": self._rig(None), "scan": None, "operator_prompt": None}
            return {"rig": self._rig(scan), "scan": self._scan_state(scan), "operator_prompt": scan.operator.prompt}

    def _rig(self, scan: _Scan | None) -> dict:
        connected = scan is not None and scan.phase in ("scanning", "cancelling")
        frame = scan.control.current if scan is not None else None
        if not connected:
            turntable = "connecting" if scan is not None and scan.phase == "connecting" else "not connected (idle between scans)"
        elif scan.control.holding:
            turntable = "holding still at the pose (paused)"
        elif frame is None:
            turntable = "moving to the first pose"
        elif frame.file != scan.latest:
            turntable = "at the pose, shooting"
        else:
            turntable = "moving to the next pose"
        return {
            "label": self.rig_label,
            "connected": connected,
            "turntable": {
                "state": turntable,
                "elevation_deg": frame.elevation_deg if frame else None,
                "azimuth_deg": frame.azimuth_deg if frame else None,
            },
            "camera": "connected" if connected else "not connected",
        }

    @staticmethod
    def _scan_state(scan: _Scan) -> dict:
        phase: str = scan.phase
        if phase in ("connecting", "scanning"):
            if scan.operator.prompt is not None:
                phase = "waiting for operator"
            elif scan.control.holding:
                phase = "paused"
            elif scan.control.paused:
                phase = "pausing"
        summary = scan.summary
        return {
            "name": scan.request.name,
            "folder": str(scan.folder),
            "request": asdict(scan.request),
            "phase": phase,
            "done": scan.done,
            "total": scan.total,
            "latest": scan.latest,
            "message": scan.message,
            "seconds": round((scan.ended or time.monotonic()) - scan.started, 1),
            "shot_now": len(summary.shot) if summary else None,
            "kept": len(summary.skipped_verified) if summary else None,
            "resumable": scan.phase in ("cancelled", "failed"),
        }

    # -- the scan thread -------------------------------------------------------------------
    def _run(self, scan_function: ScanFunction, scan: _Scan) -> None:
        def progress(done: int, total: int, what: str) -> None:
            with self._lock:
                if scan.phase == "connecting":
                    scan.phase = "scanning"
                if done > scan.done and what.startswith("raw/"):
                    scan.latest = what
                scan.done, scan.total = done, total

        try:
            summary = scan_function(scan.folder, scan.request, ScanHooks(scan.control, scan.operator, progress))
        except ScanCancelledError as exc:
            self._end(scan, "cancelled", f"{exc}. The {scan.done} frames shot are kept.")
        except StationError as exc:
            self._end(scan, "failed", str(exc))
        except Exception as exc:  # a thread's error would otherwise vanish and the page say "scanning" forever
            log.exception("scan %s failed", scan.request.name)
            self._end(scan, "failed", f"{type(exc).__name__}: {exc}")
        else:
            message = f"{summary.total} frames: {len(summary.shot)} shot now, {len(summary.skipped_verified)} kept from before"
            self._end(scan, "finished", message, summary)

    def _end(self, scan: _Scan, phase: Phase, message: str, summary: ScanSummary | None = None) -> None:
        with self._lock:
            scan.phase, scan.message, scan.summary, scan.ended = phase, message, summary, time.monotonic()
        log.info("scan %s %s: %s", scan.request.name, phase, message)
