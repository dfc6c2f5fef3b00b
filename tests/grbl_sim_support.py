"""Real GRBL 1.1h firmware (grbl-sim, from ../shared/tools/grbl-sim) behind a pty, for the driver's tests.

`build_grbl_sim` compiles it once; `GrblSimBridge` runs the shared pty bridge (a separate process:
grbl-sim is GPL and only ever talked to over its serial stream) with fault controls; running this
file as a script is a `station` scan process the tests can SIGKILL:

    python tests/grbl_sim_support.py scan PORT OUT [FEED_DEG_MIN]

Its camera stores, as each frame's bytes, the work position the firmware itself reported at the
exposure (`?` through the real driver), so a test can compare every manifest pose with it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from station.capture.plan import ScanPlan
from station.capture.session import ScanSession, SessionConfig
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder
from station.turntable.grbl import Turntable, TurntableConfig
from station.turntable.link import SerialLine
from station.turntable.protocol import GrblProtocol

SHARED_GRBL_SIM = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "grbl-sim"
# The rig's steps per degree with rates fast enough to keep a scan short on a busy machine.
FAST_SETTINGS = {110: 36000.0, 111: 36000.0, 120: 3600.0, 121: 3600.0}  # 26.7 kHz steps: GRBL allows 30


def build_grbl_sim(out: Path) -> Path | None:
    """Compile grbl-sim into `out`; None when the sources or a compiler are missing."""
    if not (SHARED_GRBL_SIM / "build.sh").exists() or not all(shutil.which(t) for t in ("gcc", "make", "stdbuf")):
        return None
    done = subprocess.run(["bash", str(SHARED_GRBL_SIM / "build.sh"), str(out)], capture_output=True, text=True,
                          timeout=300, check=False)
    exe = Path(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 and done.stdout.strip() else None
    return exe if exe is not None and exe.exists() else None


class GrblSimBridge:
    """One firmware process behind `port` (a pty symlink), with its EEPROM.DAT in `workdir`."""

    def __init__(self, exe: Path, workdir: Path, eeprom: Path | None) -> None:
        self.workdir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        if eeprom is not None:
            shutil.copyfile(eeprom, workdir / "EEPROM.DAT")
        self.port = str(workdir / "ttyGRBL")
        self.log = workdir / "bridge.log"
        self._ctl = workdir / "ctl"
        os.mkfifo(self._ctl)
        env = dict(os.environ, GRBL_SIM=str(exe))
        self._proc = subprocess.Popen([sys.executable, str(SHARED_GRBL_SIM / "pty-bridge.py"), self.port, str(workdir),
                                       str(self.log), str(self._ctl)], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10.0
        while not os.path.exists(self.port):
            if time.monotonic() > deadline or self._proc.poll() is not None:
                self.close()
                raise RuntimeError(f"grbl-sim bridge did not come up in {workdir}")
            time.sleep(0.02)

    def wait_booted(self, timeout_s: float = 30.0) -> None:
        """Until the firmware's power-on banner is in the bridge's log: it ignores input before that, which is a
        second on a quiet machine and longer under load."""
        deadline = time.monotonic() + timeout_s
        while "Grbl 1.1h" not in self.traffic():
            if time.monotonic() > deadline or self._proc.poll() is not None:
                raise RuntimeError(f"grbl-sim did not boot within {timeout_s:g} s; bridge log: {self.log}")
            time.sleep(0.05)

    def control(self, command: str) -> None:
        """A bridge command: `killfw`, `startfw`, `inject HEX`, `unplug SECS`."""
        fd = os.open(self._ctl, os.O_WRONLY | os.O_NONBLOCK)
        try:
            os.write(fd, command.encode() + b"\n")
        finally:
            os.close(fd)

    def restart_firmware(self) -> None:
        """SIGKILL the firmware and start it again: the step counter restarts at zero, EEPROM stays."""
        self.control("killfw")
        time.sleep(0.2)
        self.control("startfw")

    def traffic(self) -> str:
        """Everything the bridge logged so far (bytes each way, with timestamps)."""
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                self.control("quit")
                self._proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait(5.0)


def send_lines(port: str, lines: list[str]) -> None:
    """Reset the board and send each line, as an operator's terminal would (`$n=value` goes to EEPROM)."""
    proto = GrblProtocol(SerialLine(port), lambda status: None)
    try:
        proto.handshake(5.0)
        for line in lines:
            proto.command(line, 2.0)
    finally:
        proto.line.close()


def fast_config(feed_deg_min: float = 36000.0) -> TurntableConfig:
    """The driver's view of FAST_SETTINGS; a lower feed leaves time to act on a running move."""
    return TurntableConfig(max_rate_deg_min=(FAST_SETTINGS[110], FAST_SETTINGS[111]),
                           accel_deg_s2=(FAST_SETTINGS[120], FAST_SETTINGS[121]), feed_deg_min=feed_deg_min,
                           reply_timeout_s=3.0, banner_timeout_s=5.0, reconnect_timeout_s=20.0)


@dataclass
class _Shot:
    data: bytes

    def download(self) -> bytes:
        return self.data


class FirmwarePositionCamera:
    """Stands in for the camera: each frame's bytes are the firmware's own work position at the shot."""

    def __init__(self, table: Turntable) -> None:
        self.table = table

    def configure(self, exposure_s: float, iso: int) -> None:
        """Exposure has no meaning here."""

    def trigger(self) -> _Shot:
        status = self.table.status()
        return _Shot(json.dumps({"work": self.table.position(), "mpos": status.mpos, "state": status.state}).encode())


class _NoOperator:
    def request(self, action: str, message: str) -> None:
        """Nobody places a stone on firmware alone."""


PLAN = ScanPlan(elevations_deg=(20.0, 45.0), azimuths=4)  # 2 plates + 8 shots


def scan(port: str, out: Path, feed_deg_min: float = 36000.0) -> None:
    """One `station` scan process: connect, run (or resume) PLAN into `out`."""
    with Turntable.connect(port, fast_config(feed_deg_min)) as table:
        session = ScanSession(ScanFolder(out), PLAN, RigGeometry().scaled(32, 24), table, FirmwarePositionCamera(table),
                              _NoOperator(), "real-firmware", SessionConfig(bytes_per_frame_hint=1024, device_retries=3))
        session.run()


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.argv[1] == "scan":
        scan(sys.argv[2], Path(sys.argv[3]), *(float(v) for v in sys.argv[4:5]))
