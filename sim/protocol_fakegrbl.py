"""pyserial URL handler `fakegrbl://NAME`: a serial port whose far end is an emulated board.

pyserial's `serial_for_url()` imports `protocol_<scheme>` from each package in
`serial.protocol_handler_packages`; `sim.grbl_links.register_url_scheme()` adds "sim" to that list,
and this module's `Serial` then serves the device registered under NAME in `DEVICES`. Devices are
registered by whoever builds them (never at import). Opening an unknown or unplugged NAME fails
like a missing /dev node; once the device's link drops, every read and write raises
SerialException as a USB unplug does.
"""

from __future__ import annotations

import time
from typing import Protocol

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

SCHEME = "fakegrbl://"


class ByteDevice(Protocol):
    """What a link needs from an emulated board."""

    plugged: bool
    generation: int  # bumps whenever the link drops

    def write(self, data: bytes) -> None: ...

    def read(self) -> bytes: ...


DEVICES: dict[str, ByteDevice] = {}


class Serial(SerialBase):
    """A pyserial port object talking to `DEVICES[NAME]` in-process."""

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        name = str(self._port)[len(SCHEME):] if str(self._port).lower().startswith(SCHEME) else str(self._port)
        device = DEVICES.get(name)
        if device is not None:
            device.read()  # lets the device's clock run, so a replugged board can come back
        if device is None or not device.plugged:
            raise SerialException(f"could not open port {self._port}: no such device")
        self._device = device
        self._generation = device.generation
        self._rx = bytearray()  # what the board said before we opened is lost, as with pyserial's open()
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _live(self) -> ByteDevice:
        if not self.is_open:
            raise PortNotOpenError()
        device = self._device
        if not device.plugged or device.generation != self._generation:
            raise SerialException(f"device {self._port} disconnected")
        return device

    def _pump(self) -> None:
        self._rx += self._live().read()

    @property
    def in_waiting(self) -> int:
        self._pump()
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            self._pump()
            if len(self._rx) >= size or (deadline is not None and time.monotonic() >= deadline):
                out = bytes(self._rx[:size])
                del self._rx[:size]
                return out
            time.sleep(0.001)

    def write(self, data: bytes) -> int:
        self._live().write(bytes(data))
        return len(data)

    def flush(self) -> None:
        self._live()

    def reset_input_buffer(self) -> None:
        self._pump()
        self._rx.clear()

    def reset_output_buffer(self) -> None:
        self._live()

    def _reconfigure_port(self) -> None:
        """Baud rate and framing have no meaning in-process."""

    def _update_dtr_state(self) -> None:
        """DTR does not reset the emulated board (the driver resets it with 0x18)."""

    def _update_rts_state(self) -> None:
        """RTS has no effect on the emulated board."""

    def _update_break_state(self) -> None:
        """Break has no effect on the emulated board."""
