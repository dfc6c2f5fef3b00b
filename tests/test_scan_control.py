"""The session's control hook: a pause holds the rig at rest between frames, a cancel leaves the scan resumable.

The rig is the simulated one behind the real drivers, as in test_scan_session.py.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

from sim.rig import build_sim_rig, make_stone
from station.capture.plan import ScanPlan
from station.capture.session import ScanCancelledError, ScanControl, ScanSession, ScanSummary
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder

SMALL = RigGeometry().scaled(96, 72)
PLAN = ScanPlan(elevations_deg=(15.0, 50.0), azimuths=4)  # 2 plates + 8 shots


def _run(out: Path, control: ScanControl, on_frame=None) -> ScanSummary:
    """One session on a fresh simulated rig; `on_frame(done)` runs after each stored frame."""

    def progress(done: int, total: int, what: str) -> None:
        if on_frame is not None and what.startswith("raw/"):
            on_frame(done)

    with build_sim_rig(make_stone(None), SMALL, time_scale=0.01) as rig:
        session = ScanSession(ScanFolder(out), PLAN, SMALL, rig.turntable, rig.camera, rig.operator, "sim-stone",
                              progress=progress, control=control)
        return session.run()


def _wait_until(condition, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.02)


@contextmanager
def _scanning_in_background(out: Path, control: ScanControl, on_frame) -> Iterator[dict]:
    """Run the session on a thread; on leaving, wait for it to end (cancelling it if the test failed)."""
    outcome: dict = {}

    def scan() -> None:
        try:
            outcome["summary"] = _run(out, control, on_frame)
        except ScanCancelledError as exc:
            outcome["cancelled"] = exc

    worker = threading.Thread(target=scan, daemon=True)
    worker.start()
    try:
        yield outcome
    except BaseException:
        control.cancel()
        worker.join(timeout=30)
        raise
    worker.join(timeout=30)
    assert not worker.is_alive(), "the session did not end"


def test_a_pause_holds_the_session_before_the_next_frame_until_resumed(tmp_path):
    control = ScanControl()
    with _scanning_in_background(tmp_path / "scan", control, lambda done: done == 3 and control.pause()) as outcome:
        _wait_until(lambda: control.holding)
        assert control.current == PLAN.frames()[3], "held at the fourth frame's pose, before exposing it"
        time.sleep(0.3)
        assert len(ScanFolder(tmp_path / "scan").read_manifest()) == 3, "nothing is shot while paused"
        control.resume()
    assert len(outcome["summary"].shot) == len(PLAN.frames())
    assert ScanFolder(tmp_path / "scan").is_done("capture")


def test_a_cancel_stops_between_frames_and_the_next_run_resumes_keeping_every_frame(tmp_path):
    control = ScanControl()
    with pytest.raises(ScanCancelledError, match="resume"):
        _run(tmp_path / "scan", control, lambda done: done == 5 and control.cancel())
    scan = ScanFolder(tmp_path / "scan")
    kept = scan.read_manifest()
    assert [e.file for e in kept] == [f.file for f in PLAN.frames()[:5]]
    assert all(scan.verify_entry(e) for e in kept) and not scan.is_done("capture")

    summary = _run(tmp_path / "scan", ScanControl())
    assert sorted(summary.skipped_verified) == sorted(e.file for e in kept)
    assert len(summary.shot) == len(PLAN.frames()) - 5
    assert scan.is_done("capture")


def test_a_cancel_while_paused_wakes_the_session_and_stops_it(tmp_path):
    control = ScanControl()
    with _scanning_in_background(tmp_path / "scan", control, lambda done: done == 2 and control.pause()) as outcome:
        _wait_until(lambda: control.holding)
        control.cancel()
    assert "cancelled" in outcome
    assert len(ScanFolder(tmp_path / "scan").read_manifest()) == 2
