"""How a driver reaches an emulated board through pyserial's real code path: a pty or a URL.

- pty: a thread owns `pty.openpty()` (slave set raw with `tty.setraw`) and pumps bytes between the
  master and the emulator; the driver opens the slave by name. The port handed out is a stable
  symlink (as udev's /dev/serial/by-id is), re-pointed to a fresh pty when an unplugged board
  returns; an unplug closes the master, so the driver's reads fail as on a USB unplug.
- url: `fakegrbl://NAME` via `sim.protocol_fakegrbl`, registered on demand.

`start_fake_turntable()` builds both ends for tests and the CLI's --sim wiring.
"""

from __future__ import annotations

import itertools
import os
import pty
import select
import shutil
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Literal

import serial

from sim import protocol_fakegrbl
from sim.grbl_firmware import RIG_SETTINGS, GrblFirmware
from sim.protocol_fakegrbl import ByteDevice

_names = itertools.count()


def register_url_scheme() -> None:
    """Make `serial.serial_for_url("fakegrbl://NAME")` find `sim.protocol_fakegrbl` (idempotent)."""
    if "sim" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("sim")


class PtyLink:
    """Pumps one device over a pty, behind a symlink that survives unplug/replug."""

    def __init__(self, device: ByteDevice, link_path: Path) -> None:
        self.device = device
        self.link_path = link_path
        self._stop = threading.Event()
        self._fds: tuple[int, int] | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"pty-link {link_path.name}", daemon=True)
        self._thread.start()
        if not self._ready.wait(5.0):
            raise RuntimeError(f"pty link {link_path} did not come up")

    def _open(self) -> None:
        master, slave = pty.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        tmp = self.link_path.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.link_path)
        self._fds = (master, slave)
        self._generation = self.device.generation

    def _close(self) -> None:
        if self._fds is not None:
            for fd in self._fds:
                os.close(fd)
            self._fds = None
            self.link_path.unlink(missing_ok=True)

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self._fds is None or self.device.generation != self._generation or not self.device.plugged:
                    self._close()
                    self.device.read()  # advances the device clock, so a replug can happen
                    if not self.device.plugged:
                        time.sleep(0.005)
                        continue
                    self._open()
                    self._ready.set()
                master = self._fds[0]
                readable, _, _ = select.select([master], [], [], 0.002)
                if readable:
                    try:
                        self.device.write(os.read(master, 4096))
                    except OSError:
                        pass  # EIO: no process has the slave open right now
                out = self.device.read()
                if out and self.device.plugged:
                    try:
                        os.write(master, out)
                    except BlockingIOError:
                        pass  # nobody is reading and the pty buffer is full: bytes are lost, as on a wire
        finally:
            self._close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


class NmeaDevice:
    """A wrong device on the port: a GPS module that streams NMEA sentences whatever it is sent."""

    def __init__(self) -> None:
        self.plugged = True
        self.generation = 0
        self._last = 0.0

    def write(self, data: bytes) -> None:
        """A GPS ignores what it is sent."""

    def read(self) -> bytes:
        now = time.monotonic()
        if now - self._last < 0.05:
            return b""
        self._last = now
        return b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"


class SilentDevice:
    """A port with something dead behind it (unpowered board, wrong baud rate): it never answers."""

    def __init__(self) -> None:
        self.plugged = True
        self.generation = 0

    def write(self, data: bytes) -> None:
        """Nothing listens."""

    def read(self) -> bytes:
        return b""


@dataclass
class FakeTurntable:
    """An emulated board and the port string to hand the driver; close() tears the link down."""

    port: str
    device: ByteDevice
    route: Literal["url", "pty"]
    _pty: PtyLink | None = None
    _tmpdir: Path | None = None
    _name: str = field(default="")

    @property
    def firmware(self) -> GrblFirmware:
        if not isinstance(self.device, GrblFirmware):
            raise TypeError(f"{self.port} is not an emulated GRBL board")
        return self.device

    def close(self) -> None:
        if self._pty is not None:
            self._pty.stop()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
        protocol_fakegrbl.DEVICES.pop(self._name, None)

    def __enter__(self) -> FakeTurntable:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def attach(device: ByteDevice, route: Literal["url", "pty"] = "url") -> FakeTurntable:
    """Expose any emulated serial device on a fresh pty or `fakegrbl://` name."""
    name = f"board{next(_names)}-{os.getpid()}"
    if route == "url":
        register_url_scheme()
        protocol_fakegrbl.DEVICES[name] = device
        return FakeTurntable(f"{protocol_fakegrbl.SCHEME}{name}", device, route, _name=name)
    if route == "pty":
        tmpdir = Path(tempfile.mkdtemp(prefix="fakegrbl-"))
        link = PtyLink(device, tmpdir / "ttyGRBL")
        return FakeTurntable(str(link.link_path), device, route, _pty=link, _tmpdir=tmpdir)
    raise ValueError(f"unknown route {route!r}; expected 'url' or 'pty'")


def start_fake_turntable(route: Literal["url", "pty"] = "url", settings: dict[int, float] | None = None,
                         **firmware_kwargs: object) -> FakeTurntable:
    """A board loaded with the rig's settings (RIG_SETTINGS, then `settings`), exposed; a context manager.

    A bare GrblFirmware() has GRBL's factory settings, as a new board does.
    """
    return attach(GrblFirmware(settings=RIG_SETTINGS | (settings or {}), **firmware_kwargs), route)
