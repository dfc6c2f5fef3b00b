"""A pure-Python pyusb backend that plugs simulated devices into pyusb's real API.

`usb.core.find(..., backend=SimUsbBackend(camera))` returns an ordinary `usb.core.Device`;
`set_configuration`, `usb.util.find_descriptor`, endpoint `read`/`write` and `ctrl_transfer`
then run pyusb's own code and end here. Errors mirror the libusb-1.0 backend's (same strerror,
backend code and errno), so the driver's error mapping is exercised as it would be on hardware:
a timeout is `USBTimeoutError` (ETIMEDOUT), an unplugged device `USBError` with ENODEV.
"""

from __future__ import annotations

import array
import errno
import time
from dataclasses import dataclass, field
from typing import Any

import usb.backend
import usb.core
import usb.util

from sim.ptp_camera import SimPtpCamera
from station.capture.ptp_codec import PtpProtocolError
from station.capture.transport import PTP_INTERFACE_CLASS, CameraNotFoundError, has_ptp_interface

_NO_DEVICE = ("No such device (it may have been disconnected)", -4, errno.ENODEV)
_BUSY = ("Resource busy", -6, errno.EBUSY)
_TIMEOUT = ("Operation timed out", -7, errno.ETIMEDOUT)
_PIPE = ("Pipe error", -9, errno.EPIPE)
_NOT_FOUND = ("Entity not found", -5, errno.ENOENT)
_SPEED_HIGH = 3


@dataclass
class DeviceDescriptor:
    idVendor: int
    idProduct: int
    bus: int
    address: int
    bLength: int = 18
    bDescriptorType: int = 1
    bcdUSB: int = 0x0200
    bDeviceClass: int = 0  # class defined per interface, as cameras do
    bDeviceSubClass: int = 0
    bDeviceProtocol: int = 0
    bMaxPacketSize0: int = 64
    bcdDevice: int = 0x0100
    iManufacturer: int = 0  # no string descriptors: pyusb then never asks for them
    iProduct: int = 0
    iSerialNumber: int = 0
    bNumConfigurations: int = 1
    port_number: int = 1
    port_numbers: tuple[int, ...] = (1,)
    speed: int = _SPEED_HIGH


@dataclass
class ConfigurationDescriptor:
    wTotalLength: int
    bLength: int = 9
    bDescriptorType: int = 2
    bNumInterfaces: int = 1
    bConfigurationValue: int = 1
    iConfiguration: int = 0
    bmAttributes: int = 0xC0  # self-powered
    bMaxPower: int = 50
    extra_descriptors: list[int] = field(default_factory=list)


@dataclass
class InterfaceDescriptor:
    bInterfaceClass: int
    bInterfaceSubClass: int
    bInterfaceProtocol: int
    bNumEndpoints: int
    bLength: int = 9
    bDescriptorType: int = 4
    bInterfaceNumber: int = 0
    bAlternateSetting: int = 0
    iInterface: int = 0
    extra_descriptors: list[int] = field(default_factory=list)


@dataclass
class EndpointDescriptor:
    bEndpointAddress: int
    bmAttributes: int
    wMaxPacketSize: int
    bInterval: int = 0
    bLength: int = 7
    bDescriptorType: int = 5
    bRefresh: int = 0
    bSynchAddress: int = 0
    extra_descriptors: list[int] = field(default_factory=list)


EP_BULK_OUT, EP_BULK_IN, EP_EVENT_IN = 0x01, 0x82, 0x83


@dataclass
class SimUsbDevice:
    """One plugged-in device: descriptors, USB state, and the function behind the pipes (if any)."""

    vendor_id: int
    product_id: int
    interface_class: tuple[int, int, int] = PTP_INTERFACE_CLASS
    function: SimPtpCamera | None = None
    address: int = 2
    configuration: int = 0  # 0 = unconfigured, as after enumeration
    claimed: dict[int, object] = field(default_factory=dict)  # interface number -> handle

    @staticmethod
    def for_camera(camera: SimPtpCamera, address: int = 2) -> "SimUsbDevice":
        return SimUsbDevice(camera.vendor_id, camera.product_id, PTP_INTERFACE_CLASS, camera, address)

    @property
    def connected(self) -> bool:
        return self.function is None or self.function.connected

    def endpoints(self) -> list[EndpointDescriptor]:
        bulk = self.function.bulk_packet if self.function else 512
        event = self.function.event_packet if self.function else 64
        return [
            EndpointDescriptor(EP_BULK_OUT, usb.util.ENDPOINT_TYPE_BULK, bulk),
            EndpointDescriptor(EP_BULK_IN, usb.util.ENDPOINT_TYPE_BULK, bulk),
            EndpointDescriptor(EP_EVENT_IN, usb.util.ENDPOINT_TYPE_INTR, event, bInterval=4),
        ]


class _Handle:
    def __init__(self, device: SimUsbDevice) -> None:
        self.device = device


def _error(spec: tuple[str, int, int], timeout: bool = False) -> usb.core.USBError:
    cls = usb.core.USBTimeoutError if timeout else usb.core.USBError
    return cls(spec[0], spec[1], spec[2])


class SimUsbBackend(usb.backend.IBackend):
    """pyusb backend over simulated devices (cameras are wrapped in a SimUsbDevice automatically)."""

    def __init__(self, *devices: SimPtpCamera | SimUsbDevice) -> None:
        self.devices = [
            d if isinstance(d, SimUsbDevice) else SimUsbDevice.for_camera(d, address=2 + i) for i, d in enumerate(devices)
        ]

    # -- enumeration and descriptors ---------------------------------------------------------
    def enumerate_devices(self) -> list[SimUsbDevice]:
        return [d for d in self.devices if d.connected]

    def get_parent(self, dev: SimUsbDevice) -> None:
        return None

    def get_device_descriptor(self, dev: SimUsbDevice) -> DeviceDescriptor:
        return DeviceDescriptor(dev.vendor_id, dev.product_id, bus=1, address=dev.address)

    def get_configuration_descriptor(self, dev: SimUsbDevice, config: int) -> ConfigurationDescriptor:
        if config != 0:
            raise IndexError(f"configuration index {config} out of range")
        return ConfigurationDescriptor(wTotalLength=9 + 9 + 7 * len(dev.endpoints()))

    def get_interface_descriptor(self, dev: SimUsbDevice, intf: int, alt: int, config: int) -> InterfaceDescriptor:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"interface {intf} alt {alt} of configuration {config} out of range")
        return InterfaceDescriptor(*dev.interface_class, bNumEndpoints=len(dev.endpoints()))

    def get_endpoint_descriptor(self, dev: SimUsbDevice, ep: int, intf: int, alt: int, config: int) -> EndpointDescriptor:
        self.get_interface_descriptor(dev, intf, alt, config)
        return dev.endpoints()[ep]

    # -- device state ------------------------------------------------------------------------
    def _live(self, handle: _Handle) -> SimUsbDevice:
        if not handle.device.connected:
            raise _error(_NO_DEVICE)
        return handle.device

    def open_device(self, dev: SimUsbDevice) -> _Handle:
        if not dev.connected:
            raise _error(_NO_DEVICE)
        return _Handle(dev)

    def close_device(self, dev_handle: _Handle) -> None:
        for number, owner in list(dev_handle.device.claimed.items()):
            if owner is dev_handle:
                del dev_handle.device.claimed[number]

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        if config_value not in (0, 1):
            raise _error(_NOT_FOUND)
        self._live(dev_handle).configuration = config_value

    def get_configuration(self, dev_handle: _Handle) -> int:
        return self._live(dev_handle).configuration

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        if (intf, altsetting) != (0, 0):
            raise _error(_NOT_FOUND)
        self._live(dev_handle)

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        device = self._live(dev_handle)
        if device.claimed.get(intf, dev_handle) is not dev_handle:
            raise _error(_BUSY)  # another program holds the camera
        device.claimed[intf] = dev_handle

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        if dev_handle.device.claimed.get(intf) is dev_handle:
            del dev_handle.device.claimed[intf]
        self._live(dev_handle)

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        return False

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        return None

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        return None

    def reset_device(self, dev_handle: _Handle) -> None:
        device = self._live(dev_handle)
        device.configuration = 0
        if device.function is not None:
            device.function.reset()

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        self._live(dev_handle)

    # -- transfers ---------------------------------------------------------------------------
    def _function(self, dev_handle: _Handle) -> SimPtpCamera:
        device = self._live(dev_handle)
        if device.function is None or device.configuration == 0:
            raise _error(_PIPE)  # nothing answers: an unconfigured or function-less device stalls
        return device.function

    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: array.array, timeout: int) -> int:
        self._function(dev_handle).bulk_out(data.tobytes())
        return len(data)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        camera = self._function(dev_handle)
        chunk = camera.bulk_in(len(buff))
        if chunk is None:
            # Bulk-IN data only ever follows a host write, so waiting cannot help: spend the timeout.
            time.sleep(timeout / 1000 if timeout else 0.0)
            raise _error(_TIMEOUT, timeout=True)
        buff[: len(chunk)] = array.array("B", chunk)
        return len(chunk)

    def intr_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        camera = self._function(dev_handle)
        deadline = time.monotonic() + timeout / 1000
        while True:
            event = camera.interrupt_in(len(buff))
            if event is not None:
                buff[: len(event)] = array.array("B", event)
                return len(event)
            due, now = camera.next_event_due(), time.monotonic()
            if due is None or due > deadline:
                time.sleep(max(0.0, deadline - now))
                raise _error(_TIMEOUT, timeout=True)
            time.sleep(max(0.0, due - now))

    def ctrl_transfer(
        self, dev_handle: _Handle, bmRequestType: int, bRequest: int, wValue: int, wIndex: int, data: array.array, timeout: int
    ) -> Any:
        kind = bmRequestType & (3 << 5)
        recipient = bmRequestType & 3
        if kind != usb.util.CTRL_TYPE_CLASS or recipient != usb.util.CTRL_RECIPIENT_INTERFACE or wIndex & 0xFF != 0:
            raise _error(_PIPE)  # standard requests (strings, features) are not modelled: stall
        camera = self._function(dev_handle)
        try:
            if usb.util.ctrl_direction(bmRequestType) == usb.util.CTRL_OUT:
                camera.class_request(bRequest, data.tobytes())
                return len(data)
            answer = camera.class_request(bRequest, b"")[: len(data)]
        except PtpProtocolError:
            raise _error(_PIPE) from None  # an unknown class request stalls endpoint 0
        data[: len(answer)] = array.array("B", answer)
        return len(answer)


def find_sim_camera(camera: SimPtpCamera) -> usb.core.Device:
    """The camera as pyusb sees it: an ordinary `usb.core.Device` on its own simulated bus."""
    device = usb.core.find(backend=SimUsbBackend(camera), custom_match=has_ptp_interface)
    if device is None:
        raise CameraNotFoundError("simulated camera is not plugged in (it was disconnected)")
    return device
