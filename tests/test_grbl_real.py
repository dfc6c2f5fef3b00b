"""The turntable driver against real GRBL 1.1h firmware (grbl-sim), through pyserial on a pty.

grbl-sim is built once per run from ../shared/tools/grbl-sim; without it (or without gcc) these
tests skip. Its settings are the rig's steps per degree with high rates, so moves are short.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from grbl_sim_support import FAST_SETTINGS, PLAN, SHARED_GRBL_SIM, GrblSimBridge, build_grbl_sim, fast_config, send_lines
from station.scanfolder import ScanFolder
from station.turntable.errors import GrblSettingsError, MoveCancelledError
from station.turntable.grbl import Turntable

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]
STEP = 1.5 / 44.444 + 2e-3  # GRBL lands on whole motor steps; reports carry 3 decimals
SUPPORT = Path(__file__).with_name("grbl_sim_support.py")


@pytest.fixture(scope="session")
def grbl_sim(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(grbl_sim.exe, an EEPROM.DAT with the fast rig settings), built once per test run."""
    exe = build_grbl_sim(tmp_path_factory.mktemp("grbl-build"))
    if exe is None:
        pytest.skip(f"grbl-sim cannot be built here (needs gcc, make, stdbuf and {SHARED_GRBL_SIM})")
    bridge = GrblSimBridge(exe, tmp_path_factory.mktemp("grbl-eeprom"), SHARED_GRBL_SIM / "EEPROM.rig.DAT")
    try:
        send_lines(bridge.port, [f"${n}={v:g}" for n, v in FAST_SETTINGS.items()])
    finally:
        bridge.close()
    return exe, bridge.workdir / "EEPROM.DAT"


@pytest.fixture
def firmware(grbl_sim: tuple[Path, Path], tmp_path: Path) -> Iterator[GrblSimBridge]:
    exe, eeprom = grbl_sim
    bridge = GrblSimBridge(exe, tmp_path / "fw", eeprom)
    try:
        yield bridge
    finally:
        bridge.close()


def angle_error(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def scan_process(port: str, out: Path, feed_deg_min: float = 36000.0) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(SUPPORT), "scan", port, str(out), str(feed_deg_min)],
                            env=dict(os.environ), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def listed(out: Path) -> int:
    try:
        return len(ScanFolder(out).read_manifest())
    except Exception:  # noqa: BLE001 - the manifest is being replaced atomically right now
        return 0


def wait_frames(proc: subprocess.Popen, out: Path, count: int, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while listed(out) < count:
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline, f"only {listed(out)} frames after {timeout_s} s"
        time.sleep(0.05)


def assert_shot_where_the_firmware_stood(out: Path) -> None:
    """Every frame of PLAN is listed once, and its pose is the work position the firmware reported."""
    scan = ScanFolder(out)
    entries = scan.read_manifest()
    assert sorted(e.file for e in entries) == sorted(f.file for f in PLAN.frames())
    for entry in entries:
        seen = json.loads(scan.resolve_inside(entry.file).read_bytes())
        work = seen["work"]
        assert angle_error(work[0], entry.azimuth_deg) < STEP, (entry.file, seen)
        assert abs(work[1] - entry.elevation_deg) < STEP, (entry.file, seen)
        assert -360.0 - STEP <= work[0] <= 360.0 + STEP  # X kept bounded, not counted up ring after ring


def test_a_small_scan_on_real_firmware_shoots_every_frame_where_the_firmware_stands(firmware, tmp_path):
    proc = scan_process(firmware.port, tmp_path / "scan")
    assert proc.wait(240) == 0, proc.stderr.read().decode()[-2000:]
    assert_shot_where_the_firmware_stood(tmp_path / "scan")
    assert "G21 G90 G94" in firmware.traffic() and "G92 " not in firmware.traffic()


def test_sigkill_mid_move_then_resume_holds_the_moving_table_before_its_reset(firmware, tmp_path):
    out = tmp_path / "scan"
    proc = scan_process(firmware.port, out, feed_deg_min=3600.0)  # 90 degrees take over 1.5 s
    wait_frames(proc, out, 3)
    moves = firmware.traffic().count("G90 G1")
    while firmware.traffic().count("G90 G1") == moves:
        assert proc.poll() is None
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)  # the line went out: GRBL keeps running the move it took
    proc.wait(10)
    killed_at = len(firmware.traffic())
    again = scan_process(firmware.port, out)
    assert again.wait(240) == 0, again.stderr.read().decode()[-2000:]
    assert_shot_where_the_firmware_stood(out)
    after = firmware.traffic()[killed_at:]
    assert "ALARM:3" not in firmware.traffic()  # the reset never caught it moving...
    assert "<Run|" in after and "H>F b'!'" in after  # ...because it was found moving and held first


def test_firmware_restart_mid_scan_then_station_restart_keeps_the_reference(firmware, tmp_path):
    out = tmp_path / "scan"
    proc = scan_process(firmware.port, out)
    wait_frames(proc, out, 3)
    firmware.restart_firmware()  # MPos restarts at zero: the driver re-references with G10 L20 P1
    wait_frames(proc, out, 6)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    again = scan_process(firmware.port, out)  # connect soft-resets: a G92 reference would be gone now
    assert again.wait(240) == 0, again.stderr.read().decode()[-2000:]
    assert_shot_where_the_firmware_stood(out)
    assert "G10 L20 P1" in firmware.traffic()


def test_feed_hold_waits_on_real_firmware_and_cancel_resets_only_from_hold_0(firmware):
    with Turntable.connect(firmware.port, fast_config(feed_deg_min=1800.0)) as table:
        moving = table.move_to(90.0, 10.0)  # 3 s at 1800 degree/min on an idle machine
        time.sleep(0.3)
        table.feed_hold()
        time.sleep(1.0)
        assert not moving.done  # the move waits through the hold instead of failing
        table.resume(timeout=10.0)  # sent only once the firmware reported Hold:0
        assert moving.wait(60.0) == pytest.approx((90.0, 10.0), abs=STEP)
        assert "<Hold:0|" in firmware.traffic()  # Hold:1 lasts milliseconds at these accelerations
        moving = table.move_to(0.0, 0.0)
        time.sleep(0.3)
        table.cancel(timeout=10.0)
        with pytest.raises(MoveCancelledError):
            moving.wait(30.0)
        stopped = table.position()
        assert 0.0 < stopped[0] < 90.0 and table.status().state == "Idle"
    assert "ALARM:3" not in firmware.traffic()
    with Turntable.connect(firmware.port, fast_config()) as table:  # a fresh connect reads the same position
        assert table.position() == pytest.approx(stopped, abs=STEP)


def test_a_stored_g20_startup_line_does_not_turn_degrees_into_inches(firmware):
    send_lines(firmware.port, ["$N0=G20"])
    with Turntable.connect(firmware.port, fast_config()) as table:
        assert table.info.startup_lines == ("G20",)
        assert table.move_to(20.0, 5.0).wait(30.0) == pytest.approx((20.0, 5.0), abs=STEP)
        assert table.status().mpos[0] - table.reference.wco[0] == pytest.approx(20.0, abs=STEP)
    assert ">G20:ok" in firmware.traffic()


def test_factory_settings_are_refused_naming_each_mismatch(grbl_sim, tmp_path):
    exe, _ = grbl_sim
    bridge = GrblSimBridge(exe, tmp_path / "factory", None)  # no EEPROM.DAT: GRBL's factory defaults
    try:
        with pytest.raises(GrblSettingsError, match=r"\$100=250 \(expected 44.444.*\$110=500.*\$120=10"):
            Turntable.connect(bridge.port, fast_config())
    finally:
        bridge.close()
