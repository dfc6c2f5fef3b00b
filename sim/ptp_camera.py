"""A simulated PTP camera: the responder side of ISO 15740 over the USB Still Image Class.

It speaks bytes exactly as a camera's bulk and interrupt endpoints would, so the real driver
runs unchanged on top of it through pyusb (see `sim/usb_backend.py`). Sessions, transaction
ids, one storage, objects, the event queue and two properties (ExposureTime, ExposureIndex)
behave as the standard says; `PtpFaults` injects the failures a real camera shows. The image
itself comes from a caller-supplied `frame_source`, so the rig builder decides what is seen.
Time is real but scaled by `time_scale` (0 makes captures instant), so tests stay quick.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from typing import Callable

from station.capture.ptp_codec import (
    Container,
    ContainerType,
    DataType,
    DeviceInfo,
    DevicePropCode,
    DevicePropDesc,
    EventCode,
    ObjectFormat,
    ObjectInfo,
    OperationCode,
    PropRange,
    PtpProtocolError,
    ResponseCode,
    U32_MAX,
    decode_header,
    decode_value,
    encode_container,
    encode_device_info,
    encode_object_info,
    encode_prop_desc,
    encode_value,
)
from station.capture.transport import CANCEL_CODE, REQUEST_CANCEL, REQUEST_DEVICE_RESET, REQUEST_GET_DEVICE_STATUS

STORAGE_ID = 0x00010001
ISO_STEPS = (100, 200, 400, 800, 1600, 3200, 6400)
_SUFFIX_FORMATS = {".dng": ObjectFormat.DNG, ".tif": ObjectFormat.TIFF, ".tiff": ObjectFormat.TIFF, ".jpg": ObjectFormat.EXIF_JPEG}


@dataclass(frozen=True)
class CaptureSettings:
    """What the camera was set to when the shutter fired; handed to the frame source."""

    exposure_s: float
    iso: int


FrameSource = Callable[[CaptureSettings], tuple[bytes, str]]  # -> (file bytes, filename)


@dataclass
class PtpFaults:
    """Failures to inject; each counter is spent as the fault fires, so a test states exactly how many."""

    busy_next: int = 0  # answer DeviceBusy to the next N operations
    drop_object_added: int = 0  # the next N captures never send ObjectAdded
    drop_capture_complete: int = 0  # the next N captures never send CaptureComplete
    chunk_bytes: int | None = None  # every bulk-IN read returns at most this many bytes
    truncate_next: int = 0  # the next N GetObject data phases stop halfway until the host cancels
    disconnect_after_bytes: int | None = None  # unplug after this many bytes of the next GetObject data phase
    corrupt_next_response: int = 0  # the next N response containers arrive as garbage bytes


class _Transfer:
    """One bulk-IN transfer as the device queues it; a read never spans two transfers."""

    def __init__(self, data: bytes, unplug_at: int | None = None) -> None:
        self.data, self.pos, self.unplug_at = data, 0, unplug_at


class SimPtpCamera:
    """One camera: a capture takes (capture_latency_s + exposure) * time_scale seconds of real time."""

    vendor_id = 0x1209  # pid.codes, whose product ids 0x0001-0x0010 are reserved for testing
    product_id = 0x0001
    bulk_packet = 512  # high-speed bulk wMaxPacketSize
    event_packet = 64

    def __init__(
        self,
        frame_source: FrameSource,
        *,
        capture_latency_s: float = 0.02,
        time_scale: float = 1.0,
        faults: PtpFaults | None = None,
        max_objects: int = 64,
        model: str = "Sim PTP Camera",
        serial: str = "SIM-0001",
    ) -> None:
        self.frame_source = frame_source
        self.capture_latency_s = capture_latency_s
        self.time_scale = time_scale
        self.faults = faults or PtpFaults()
        self.max_objects = max_objects
        self.info = DeviceInfo(
            operations_supported=tuple(OperationCode),
            events_supported=(EventCode.ObjectAdded, EventCode.DevicePropChanged, EventCode.StoreFull, EventCode.CaptureComplete),
            device_properties_supported=(DevicePropCode.ExposureTime, DevicePropCode.ExposureIndex),
            capture_formats=(ObjectFormat.DNG,),
            image_formats=(ObjectFormat.DNG, ObjectFormat.TIFF, ObjectFormat.EXIF_JPEG),
            manufacturer="station",
            model=model,
            device_version="1.0",
            serial_number=serial,
        )
        self.props: dict[int, DevicePropDesc] = {
            # ExposureTime: 0.1 ms units, 1/10000 s to 30 s in 0.1 ms steps (range form).
            DevicePropCode.ExposureTime: DevicePropDesc(
                DevicePropCode.ExposureTime, DataType.UINT32, True, 333, 333, range=PropRange(1, 300_000, 1)
            ),
            # ExposureIndex: full-stop ISO values (enumeration form).
            DevicePropCode.ExposureIndex: DevicePropDesc(
                DevicePropCode.ExposureIndex, DataType.UINT16, True, 100, 100, enumeration=ISO_STEPS
            ),
        }
        self.objects: dict[int, tuple[ObjectInfo, bytes, float]] = {}  # handle -> (info, data, ready_at)
        self.connected = True
        self.operations: list[tuple[int, int]] = []  # (operation code, transaction id) as received
        self.session_id: int | None = None
        self._expected_tid = 0
        self._next_handle = 1
        self._rx = bytearray()
        self._pending: Container | None = None  # a command waiting for its data phase
        self._tx: deque[_Transfer] = deque()
        self._events: list[tuple[float, bytes]] = []  # (due, container), kept sorted by due
        self._capturing_until = 0.0
        self._busy_status_polls = 0

    # -- the wire, as seen from the device -----------------------------------------------------
    def bulk_out(self, data: bytes) -> None:
        """Bytes the host wrote to bulk-OUT; each complete container is acted on."""
        self._rx += data
        while len(self._rx) >= 12:
            try:
                head = decode_header(self._rx)
            except PtpProtocolError:
                self._rx.clear()  # garbage: a real camera would stall; we drop it and stay silent
                return
            if len(self._rx) < head.length:
                return
            raw, self._rx = bytes(self._rx[: head.length]), self._rx[head.length :]
            self._receive(head.type, head.code, head.transaction_id, raw[12:])

    def bulk_in(self, size: int) -> bytes | None:
        """Up to `size` bytes of the current transfer, or None when the device has nothing to send."""
        if not self._tx:
            return None
        transfer = self._tx[0]
        limit = min(size, self.faults.chunk_bytes or size)
        end = min(len(transfer.data), transfer.pos + limit)
        if transfer.unplug_at is not None and end >= transfer.unplug_at:
            end = transfer.unplug_at
            self.connected = False
        chunk = transfer.data[transfer.pos : end]
        transfer.pos = end
        if transfer.pos >= len(transfer.data):
            self._tx.popleft()
        return chunk

    def interrupt_in(self, size: int) -> bytes | None:
        if self._events and self._events[0][0] <= time.monotonic():
            return self._events.pop(0)[1][:size]
        return None

    def next_event_due(self) -> float | None:
        return self._events[0][0] if self._events else None

    def class_request(self, request: int, data: bytes) -> bytes:
        """USB Still Image Class requests on endpoint 0; returns the IN data stage (empty for OUT)."""
        if request == REQUEST_CANCEL:
            if int.from_bytes(data[:2], "little") == CANCEL_CODE:  # then the transaction id, which any cancel ends
                self._tx.clear()
                self._rx.clear()
                self._pending = None
                self._busy_status_polls = 1  # the camera reports Busy once while it winds down
            return b""
        if request == REQUEST_DEVICE_RESET:
            self.reset()
            return b""
        if request == REQUEST_GET_DEVICE_STATUS:
            busy = self._busy_status_polls > 0
            self._busy_status_polls = max(0, self._busy_status_polls - 1)
            code = ResponseCode.DeviceBusy if busy else ResponseCode.OK
            return (4).to_bytes(2, "little") + int(code).to_bytes(2, "little")
        raise PtpProtocolError(f"sim camera: unsupported class request 0x{request:02X}")

    def reset(self) -> None:
        """Device Reset: close the session and forget queued traffic (objects stay on the card)."""
        self.session_id = None
        self._tx.clear()
        self._rx.clear()
        self._pending = None
        self._events.clear()

    # -- operations --------------------------------------------------------------------------
    def _receive(self, ctype: ContainerType, code: int, tid: int, body: bytes) -> None:
        if ctype == ContainerType.COMMAND:
            params = tuple(int.from_bytes(body[i : i + 4], "little") for i in range(0, len(body), 4))
            command = Container(ctype, code, tid, params)
            if code == OperationCode.SetDevicePropValue:
                self._pending = command
            else:
                self._operate(command, None)
        elif ctype == ContainerType.DATA and self._pending is not None and self._pending.transaction_id == tid:
            command, self._pending = self._pending, None
            self._operate(command, body)
        else:
            self._respond(tid, ResponseCode.GeneralError)

    def _operate(self, cmd: Container, data: bytes | None) -> None:
        op, tid = cmd.code, cmd.transaction_id
        self.operations.append((op, tid))
        if op == OperationCode.OpenSession:
            if self.session_id is not None:
                return self._respond(tid, ResponseCode.SessionAlreadyOpened, (self.session_id,))
            if tid != 0 or not cmd.params or cmd.params[0] == 0:
                return self._respond(tid, ResponseCode.InvalidParameter if tid == 0 else ResponseCode.InvalidTransactionID)
            self.session_id, self._expected_tid = cmd.params[0], 1
            return self._respond(tid, ResponseCode.OK)
        if self.session_id is None and op != OperationCode.GetDeviceInfo:
            return self._respond(tid, ResponseCode.SessionNotOpen)
        if self.session_id is not None:
            if tid != self._expected_tid:
                return self._respond(tid, ResponseCode.InvalidTransactionID)
            self._expected_tid = (tid + 1) % U32_MAX
        if self.faults.busy_next > 0:
            self.faults.busy_next -= 1
            return self._respond(tid, ResponseCode.DeviceBusy)
        handler = _HANDLERS.get(op)
        if handler is None:
            return self._respond(tid, ResponseCode.OperationNotSupported)
        handler(self, cmd, data)

    def _respond(self, tid: int, code: int, params: tuple[int, ...] = ()) -> None:
        raw = encode_container(Container(ContainerType.RESPONSE, code, tid, params))
        if self.faults.corrupt_next_response > 0:
            self.faults.corrupt_next_response -= 1
            raw = bytes(b ^ 0xA5 for b in raw)  # line noise: the length and type no longer make sense
        self._tx.append(_Transfer(raw))

    def _send_data(self, cmd: Container, payload: bytes, transfer: _Transfer | None = None) -> None:
        transfer = transfer or _Transfer(encode_container(Container(ContainerType.DATA, cmd.code, cmd.transaction_id, payload=payload)))
        self._tx.append(transfer)
        if len(transfer.data) % self.bulk_packet == 0:
            self._tx.append(_Transfer(b""))  # USB ends a transfer of whole packets with a zero-length packet

    def _queue_event(self, code: int, tid: int, params: tuple[int, ...], due: float) -> None:
        self._events.append((due, encode_container(Container(ContainerType.EVENT, code, tid, params))))
        self._events.sort(key=lambda e: e[0])

    def _ready_objects(self) -> dict[int, tuple[ObjectInfo, bytes, float]]:
        now = time.monotonic()
        return {h: o for h, o in self.objects.items() if o[2] <= now}

    def settings(self) -> CaptureSettings:
        exposure = int(self.props[DevicePropCode.ExposureTime].current)  # type: ignore[arg-type]
        return CaptureSettings(exposure_s=exposure / 10_000, iso=int(self.props[DevicePropCode.ExposureIndex].current))  # type: ignore[arg-type]

    def _op_close_session(self, cmd: Container, data: bytes | None) -> None:
        self.session_id = None
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_device_info(self, cmd: Container, data: bytes | None) -> None:
        self._send_data(cmd, encode_device_info(self.info))
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_storage_ids(self, cmd: Container, data: bytes | None) -> None:
        self._send_data(cmd, encode_value(DataType.AUINT32, (STORAGE_ID,)))
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_object_handles(self, cmd: Container, data: bytes | None) -> None:
        storage = cmd.params[0] if cmd.params else U32_MAX
        if storage not in (U32_MAX, STORAGE_ID):
            return self._respond(cmd.transaction_id, ResponseCode.InvalidStorageID)
        self._send_data(cmd, encode_value(DataType.AUINT32, tuple(sorted(self._ready_objects()))))
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _object(self, cmd: Container) -> tuple[ObjectInfo, bytes, float] | None:
        found = self._ready_objects().get(cmd.params[0] if cmd.params else 0)
        if found is None:
            self._respond(cmd.transaction_id, ResponseCode.InvalidObjectHandle)
        return found

    def _op_object_info(self, cmd: Container, data: bytes | None) -> None:
        if (obj := self._object(cmd)) is not None:
            self._send_data(cmd, encode_object_info(obj[0]))
            self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_get_object(self, cmd: Container, data: bytes | None) -> None:
        if (obj := self._object(cmd)) is None:
            return
        raw = encode_container(Container(ContainerType.DATA, cmd.code, cmd.transaction_id, payload=obj[1]))
        if self.faults.disconnect_after_bytes is not None:
            unplug_at, self.faults.disconnect_after_bytes = self.faults.disconnect_after_bytes, None
            return self._send_data(cmd, b"", _Transfer(raw, unplug_at=unplug_at))
        if self.faults.truncate_next > 0:
            # The data phase stops on a packet boundary and no response follows until the host cancels.
            self.faults.truncate_next -= 1
            half = (len(raw) // 2) // self.bulk_packet * self.bulk_packet
            return self._send_data(cmd, b"", _Transfer(raw[:half]))
        self._send_data(cmd, b"", _Transfer(raw))
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_partial_object(self, cmd: Container, data: bytes | None) -> None:
        if (obj := self._object(cmd)) is not None:
            offset, count = (cmd.params + (0, U32_MAX))[1:3]
            part = obj[1][offset : offset + count]
            self._send_data(cmd, part)
            self._respond(cmd.transaction_id, ResponseCode.OK, (len(part),))

    def _op_delete_object(self, cmd: Container, data: bytes | None) -> None:
        handle = cmd.params[0] if cmd.params else 0
        if handle == U32_MAX:
            self.objects.clear()
        elif self.objects.pop(handle, None) is None:
            return self._respond(cmd.transaction_id, ResponseCode.InvalidObjectHandle)
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_initiate_capture(self, cmd: Container, data: bytes | None) -> None:
        now = time.monotonic()
        if now < self._capturing_until:
            return self._respond(cmd.transaction_id, ResponseCode.DeviceBusy)
        if len(self.objects) >= self.max_objects:
            self._queue_event(EventCode.StoreFull, cmd.transaction_id, (STORAGE_ID,), now)
            return self._respond(cmd.transaction_id, ResponseCode.StoreFull)
        settings = self.settings()
        payload, filename = self.frame_source(settings)
        done = now + (self.capture_latency_s + settings.exposure_s) * self.time_scale
        handle, self._next_handle = self._next_handle, self._next_handle + 1
        suffix = "." + filename.rsplit(".", 1)[-1].lower() if "." in filename else ""
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
        info = ObjectInfo(
            storage_id=STORAGE_ID,
            object_format=_SUFFIX_FORMATS.get(suffix, ObjectFormat.Undefined),
            object_compressed_size=len(payload),
            sequence_number=handle,
            filename=filename,
            capture_date=stamp,
            modification_date=stamp,
        )
        self.objects[handle] = (info, bytes(payload), done)
        self._capturing_until = done
        if self.faults.drop_object_added > 0:
            self.faults.drop_object_added -= 1
        else:
            self._queue_event(EventCode.ObjectAdded, cmd.transaction_id, (handle,), done)
        if self.faults.drop_capture_complete > 0:
            self.faults.drop_capture_complete -= 1
        else:
            self._queue_event(EventCode.CaptureComplete, cmd.transaction_id, (cmd.transaction_id,), done)
        self._respond(cmd.transaction_id, ResponseCode.OK)

    def _prop(self, cmd: Container) -> DevicePropDesc | None:
        desc = self.props.get(cmd.params[0] if cmd.params else 0)
        if desc is None:
            self._respond(cmd.transaction_id, ResponseCode.DevicePropNotSupported)
        return desc

    def _op_prop_desc(self, cmd: Container, data: bytes | None) -> None:
        if (desc := self._prop(cmd)) is not None:
            self._send_data(cmd, encode_prop_desc(desc))
            self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_get_prop(self, cmd: Container, data: bytes | None) -> None:
        if (desc := self._prop(cmd)) is not None:
            self._send_data(cmd, encode_value(desc.data_type, desc.current))
            self._respond(cmd.transaction_id, ResponseCode.OK)

    def _op_set_prop(self, cmd: Container, data: bytes | None) -> None:
        if (desc := self._prop(cmd)) is None:
            return
        try:
            value = decode_value(desc.data_type, data or b"")
        except PtpProtocolError:
            return self._respond(cmd.transaction_id, ResponseCode.InvalidDevicePropValue)
        if not desc.writable or not desc.allows(value):
            return self._respond(cmd.transaction_id, ResponseCode.InvalidDevicePropValue)
        self.props[desc.code] = replace(desc, current=value)
        self._queue_event(EventCode.DevicePropChanged, U32_MAX, (desc.code,), time.monotonic())
        self._respond(cmd.transaction_id, ResponseCode.OK)


_HANDLERS: dict[int, Callable[[SimPtpCamera, Container, bytes | None], None]] = {
    OperationCode.GetDeviceInfo: SimPtpCamera._op_device_info,
    OperationCode.CloseSession: SimPtpCamera._op_close_session,
    OperationCode.GetStorageIDs: SimPtpCamera._op_storage_ids,
    OperationCode.GetObjectHandles: SimPtpCamera._op_object_handles,
    OperationCode.GetObjectInfo: SimPtpCamera._op_object_info,
    OperationCode.GetObject: SimPtpCamera._op_get_object,
    OperationCode.GetPartialObject: SimPtpCamera._op_partial_object,
    OperationCode.DeleteObject: SimPtpCamera._op_delete_object,
    OperationCode.InitiateCapture: SimPtpCamera._op_initiate_capture,
    OperationCode.GetDevicePropDesc: SimPtpCamera._op_prop_desc,
    OperationCode.GetDevicePropValue: SimPtpCamera._op_get_prop,
    OperationCode.SetDevicePropValue: SimPtpCamera._op_set_prop,
}
