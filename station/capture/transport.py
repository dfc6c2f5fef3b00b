"""Camera transports: the small interface a scan session drives, and PTP's USB pipes via pyusb.

`Camera` is what the session sees, so a vendor PTP flavour or a machine-vision (GenICam)
camera can be added beside the generic PTP driver without touching the session.
`UsbPtpTransport` only moves bytes over the PTP interface's three endpoints and the class
requests of the USB Still Image Class; it knows nothing of operations. It turns pyusb's
errors into the station's typed ones: a timeout is `DeviceTimeoutError`, a vanished device
(errno ENODEV) is `DeviceDisconnectedError`.
"""

from __future__ import annotations

import errno
import struct
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, Protocol

import usb.core
import usb.util

from station.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError

# USB Still Image Capture Device Definition: interface class 6 (image), subclass 1, protocol 1 (PTP).
PTP_INTERFACE_CLASS = (6, 1, 1)
REQUEST_CANCEL = 0x64
REQUEST_DEVICE_RESET = 0x66
REQUEST_GET_DEVICE_STATUS = 0x67
CANCEL_CODE = 0x4001
_CLASS_OUT = usb.util.build_request_type(usb.util.CTRL_OUT, usb.util.CTRL_TYPE_CLASS, usb.util.CTRL_RECIPIENT_INTERFACE)
_CLASS_IN = usb.util.build_request_type(usb.util.CTRL_IN, usb.util.CTRL_TYPE_CLASS, usb.util.CTRL_RECIPIENT_INTERFACE)


@dataclass(frozen=True)
class CapturedFrame:
    """One image as the camera stored it: the file bytes, untouched."""

    filename: str
    format: str  # "dng", "tiff", "jpeg" or "undefined"
    data: bytes


class Camera(Protocol):
    """What a scan session needs from any camera, whatever its wire protocol."""

    def connect(self) -> None: ...

    def describe(self) -> dict[str, str]: ...

    def set_exposure(self, seconds: float) -> float: ...

    def set_iso(self, iso: int) -> int: ...

    def capture(self) -> CapturedFrame: ...

    def close(self) -> None: ...


class PtpTransport(Protocol):
    """Byte pipes a PTP driver needs (USB today; PTP/IP would fit the same shape)."""

    description: str

    def write(self, data: bytes, timeout_ms: int) -> None: ...

    def read(self, size: int, timeout_ms: int) -> bytes: ...

    def read_event(self, timeout_ms: int) -> bytes | None: ...

    def cancel(self, transaction_id: int, timeout_ms: int) -> None: ...

    def reset(self, timeout_ms: int) -> None: ...

    def get_status(self, timeout_ms: int) -> tuple[int, tuple[int, ...]]: ...

    def clear_halt(self, endpoint: int) -> None: ...

    def close(self) -> None: ...


class CameraNotFoundError(DeviceError):
    """No USB backend, no device, or a device without a PTP interface."""


def is_ptp_interface(interface: Any) -> bool:
    return (interface.bInterfaceClass, interface.bInterfaceSubClass, interface.bInterfaceProtocol) == PTP_INTERFACE_CLASS


def has_ptp_interface(device: usb.core.Device) -> bool:
    try:
        return any(is_ptp_interface(intf) for cfg in device for intf in cfg)
    except usb.core.USBError:
        return False  # a device whose descriptors cannot be read is not a camera we can drive


def describe_usb_device(device: usb.core.Device) -> str:
    """`04a9:32b4 (interfaces 6/1/1)`: enough for an operator to see what was plugged in."""
    try:
        classes = sorted({f"{i.bInterfaceClass}/{i.bInterfaceSubClass}/{i.bInterfaceProtocol}" for cfg in device for i in cfg})
    except usb.core.USBError:
        classes = ["unreadable"]
    return f"{device.idVendor:04x}:{device.idProduct:04x} (interfaces {', '.join(classes) or 'none'})"


def _hex_or_any(value: int | None) -> str:
    return "*" if value is None else f"{value:04x}"


def _is_disconnect(error: usb.core.USBError) -> bool:
    return error.errno == errno.ENODEV or "no such device" in str(error).lower()


class UsbPtpTransport:
    """The PTP interface of one USB device: bulk-OUT, bulk-IN, interrupt-IN, and class requests."""

    def __init__(self, device: usb.core.Device) -> None:
        self.device = device
        self.description = f"camera {device.idVendor:04x}:{device.idProduct:04x}"
        try:
            self._claim()
        except BaseException:
            usb.util.dispose_resources(device)
            raise

    def _claim(self) -> None:
        device = self.device
        with self._usb_errors("configure"):
            config = self._active_configuration()
            if config is None or usb.util.find_descriptor(config, custom_match=is_ptp_interface) is None:
                device.set_configuration()
                config = device.get_active_configuration()
            interface = usb.util.find_descriptor(config, custom_match=is_ptp_interface)
            if interface is None:
                raise CameraNotFoundError(f"{describe_usb_device(device)} has no PTP interface (class 6/1/1)")
            self.interface_number = interface.bInterfaceNumber
            self._detach_kernel_driver()
            usb.util.claim_interface(device, interface)
            self.ep_out = self._endpoint(interface, usb.util.ENDPOINT_OUT, usb.util.ENDPOINT_TYPE_BULK)
            self.ep_in = self._endpoint(interface, usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_BULK)
            self.ep_event = self._endpoint(interface, usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_INTR)

    @classmethod
    def find(cls, backend: Any = None, vendor: int | None = None, product: int | None = None) -> "UsbPtpTransport":
        """The first device with a PTP interface (optionally of a given vendor:product id)."""

        def wanted(dev: usb.core.Device) -> bool:
            return (vendor is None or dev.idVendor == vendor) and (product is None or dev.idProduct == product)

        try:
            found = usb.core.find(backend=backend, custom_match=lambda d: wanted(d) and has_ptp_interface(d))
            if found is None:
                seen = [describe_usb_device(d) for d in usb.core.find(find_all=True, backend=backend)]
        except usb.core.NoBackendError:
            raise CameraNotFoundError("no USB backend available (libusb-1.0 not found), so no PTP camera can be opened") from None
        if found is None:
            want = "" if vendor is None and product is None else f" matching {_hex_or_any(vendor)}:{_hex_or_any(product)}"
            saw = "; ".join(seen) if seen else "no USB devices at all"
            raise CameraNotFoundError(f"no PTP camera (USB interface class 6/1/1){want} found; saw {saw}")
        return cls(found)

    def _active_configuration(self) -> Any:
        try:
            return self.device.get_active_configuration()
        except usb.core.USBError:
            return None

    def _detach_kernel_driver(self) -> None:
        # On Linux a desktop's gvfs/gphoto monitor may hold the interface; backends without the call are fine.
        try:
            if self.device.is_kernel_driver_active(self.interface_number):
                self.device.detach_kernel_driver(self.interface_number)
        except (NotImplementedError, usb.core.USBError):
            return

    def _endpoint(self, interface: Any, direction: int, kind: int) -> Any:
        endpoint = usb.util.find_descriptor(
            interface,
            custom_match=lambda e: usb.util.endpoint_direction(e.bEndpointAddress) == direction
            and usb.util.endpoint_type(e.bmAttributes) == kind,
        )
        if endpoint is None:
            which = ("IN" if direction else "OUT") + (" bulk" if kind == usb.util.ENDPOINT_TYPE_BULK else " interrupt")
            raise CameraNotFoundError(f"{self.description}: PTP interface lacks its {which} endpoint")
        return endpoint

    @contextmanager
    def _usb_errors(self, what: str, timeout_ms: int | None = None) -> Iterator[None]:
        try:
            yield
        except usb.core.USBTimeoutError as e:
            raise DeviceTimeoutError(f"{self.description}: {what} timed out after {timeout_ms} ms") from e
        except usb.core.USBError as e:
            if _is_disconnect(e):
                raise DeviceDisconnectedError(f"{self.description} disconnected during {what} (USB: {e.strerror or e})") from e
            raise DeviceError(f"{self.description}: USB error during {what}: {e}") from e

    def write(self, data: bytes, timeout_ms: int) -> None:
        with self._usb_errors("bulk write", timeout_ms):
            sent = self.ep_out.write(data, timeout_ms)
        if sent != len(data):
            raise DeviceError(f"{self.description}: bulk write sent {sent} of {len(data)} bytes")

    def read(self, size: int, timeout_ms: int) -> bytes:
        with self._usb_errors("bulk read", timeout_ms):
            return self.ep_in.read(size, timeout_ms).tobytes()

    def read_event(self, timeout_ms: int) -> bytes | None:
        """One event container, or None if none arrived in time (silence is normal here)."""
        try:
            with self._usb_errors("event read", timeout_ms):
                return self.ep_event.read(self.ep_event.wMaxPacketSize, timeout_ms).tobytes()
        except DeviceTimeoutError:
            return None

    def cancel(self, transaction_id: int, timeout_ms: int) -> None:
        payload = struct.pack("<HI", CANCEL_CODE, transaction_id)
        with self._usb_errors("cancel request", timeout_ms):
            self.device.ctrl_transfer(_CLASS_OUT, REQUEST_CANCEL, 0, self.interface_number, payload, timeout_ms)

    def reset(self, timeout_ms: int) -> None:
        with self._usb_errors("device reset request", timeout_ms):
            self.device.ctrl_transfer(_CLASS_OUT, REQUEST_DEVICE_RESET, 0, self.interface_number, None, timeout_ms)

    def get_status(self, timeout_ms: int) -> tuple[int, tuple[int, ...]]:
        """(response code, halted endpoint addresses) from Get Device Status."""
        with self._usb_errors("get device status", timeout_ms):
            raw = self.device.ctrl_transfer(_CLASS_IN, REQUEST_GET_DEVICE_STATUS, 0, self.interface_number, 64, timeout_ms).tobytes()
        if len(raw) < 4:
            raise DeviceError(f"{self.description}: device status is {len(raw)} bytes, needs at least 4")
        length, code = struct.unpack_from("<HH", raw)
        count = max(0, min(length, len(raw)) - 4) // 4
        return code, struct.unpack_from(f"<{count}I", raw, 4)

    def clear_halt(self, endpoint: int) -> None:
        with self._usb_errors("clear halt"):
            self.device.clear_halt(endpoint)

    def close(self) -> None:
        """Release the interface; a device already gone is not an error when closing."""
        try:
            usb.util.release_interface(self.device, self.interface_number)
        except usb.core.USBError:
            pass
        usb.util.dispose_resources(self.device)
