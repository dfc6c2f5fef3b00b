"""Line I/O over pyserial with deadlines: the only place that touches the serial port.

pyserial's `readline()` silently returns a partial line on timeout; here a read either yields a
whole line or reports that the deadline passed, and every port failure (SerialException, OSError,
a closed port) becomes DeviceDisconnectedError naming the port.
"""

from __future__ import annotations

import threading
import time

import serial

from station.errors import DeviceDisconnectedError, DeviceError

_POLL_S = 0.02  # pyserial read timeout slice: bounds how late a deadline is noticed


class SerialLine:
    """An open serial port (device path or pyserial URL) read as `\\r\\n`-terminated lines."""

    def __init__(self, port: str, baudrate: int = 115200) -> None:
        self.port = port
        try:
            self._serial = serial.serial_for_url(port, baudrate=baudrate, timeout=_POLL_S, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open turntable port {port}: {exc}") from exc
        self._buffer = bytearray()
        self._write_lock = threading.Lock()
        self.heard = bytearray()  # every byte received, kept short, to quote in error messages

    def write(self, data: bytes) -> None:
        """Send bytes (a line or a realtime byte); safe to call from a second thread."""
        with self._write_lock:
            try:
                self._serial.write(data)
                self._serial.flush()
            except (serial.SerialException, OSError, ValueError) as exc:
                raise DeviceDisconnectedError(f"turntable port {self.port} vanished while writing: {exc}") from exc

    def read_line(self, deadline: float) -> str | None:
        """Next complete line without its line ending, or None once `deadline` (monotonic) passed."""
        while True:
            cut = self._buffer.find(b"\n")
            if cut >= 0:
                raw = bytes(self._buffer[:cut])
                del self._buffer[: cut + 1]
                return raw.rstrip(b"\r").decode("ascii", errors="replace")
            try:
                waiting = self._serial.in_waiting
                if not waiting and time.monotonic() >= deadline:
                    return None
                chunk = self._serial.read(waiting or 1)  # blocks at most _POLL_S when nothing waits
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                # TypeError/AttributeError: pyserial's posix read on a descriptor closed under it.
                raise DeviceDisconnectedError(f"turntable port {self.port} vanished while reading: {exc}") from exc
            if chunk:
                self._buffer += chunk
                if len(self.heard) < 200:
                    self.heard += chunk[: 200 - len(self.heard)]

    def discard_input(self) -> None:
        """Drop anything received but not yet read (stale replies before a fresh handshake)."""
        self._buffer.clear()
        try:
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"turntable port {self.port} vanished: {exc}") from exc

    def close(self) -> None:
        try:
            self._serial.close()
        except (serial.SerialException, OSError):
            pass  # closing a vanished port has nothing left to release
