"""Generic PTP (ISO 15740) camera driver: sessions, properties, and the capture flow.

The driver speaks operations over any `PtpTransport`; it knows the wire protocol and nothing
else (retries across frames, resume and the manifest belong to the scan session). Recoveries it
owns, because only the protocol layer can perform them:
- DeviceBusy: the operation is re-sent as a new transaction, a bounded number of times with
  exponential backoff, then `DeviceBusyError` is raised.
- A data phase that stops early (truncated transfer): the transaction is cancelled with the
  USB class Cancel request, Get Device Status is polled until OK, and the read-only operation is
  re-issued a bounded number of times, then `IncompleteTransferError` is raised.
- A dropped ObjectAdded event: when CaptureComplete (or the capture deadline) arrives without
  it, the new object is found by comparing GetObjectHandles with the list taken before the
  shot. Polling was chosen over failing because the picture exists and a rescan costs minutes.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

from station.capture.ptp_codec import (
    HEADER_SIZE,
    U32_MAX,
    Container,
    ContainerHeader,
    ContainerType,
    DataType,
    DeviceBusyError,
    DeviceInfo,
    DevicePropCode,
    DevicePropDesc,
    EventCode,
    IncompleteTransferError,
    ObjectFormat,
    ObjectInfo,
    OperationCode,
    PropValue,
    PtpProtocolError,
    ResponseCode,
    SessionAlreadyOpenError,
    StoreFullError,
    code_name,
    decode_container,
    decode_device_info,
    decode_header,
    decode_object_info,
    decode_prop_desc,
    decode_value,
    encode_container,
    encode_value,
    response_error,
)
from station.capture.transport import CapturedFrame, PtpTransport, UsbPtpTransport
from station.errors import BadInputError, DeviceDisconnectedError, DeviceError, DeviceTimeoutError

log = logging.getLogger(__name__)

SESSION_ID = 1
EXPOSURE_UNITS_PER_S = 10_000  # PTP ExposureTime is in 0.1 ms
FORMAT_NAMES = {ObjectFormat.DNG: "dng", ObjectFormat.TIFF: "tiff", ObjectFormat.EXIF_JPEG: "jpeg"}


class CaptureTimeoutError(DeviceTimeoutError):
    """InitiateCapture was accepted but no new object appeared before the capture deadline."""


@dataclass
class PtpConfig:
    timeout_ms: int = 5000  # per bulk transfer
    capture_timeout_s: float = 30.0  # InitiateCapture until CaptureComplete
    complete_grace_s: float = 2.0  # after ObjectAdded, how long CaptureComplete may lag
    event_poll_ms: int = 200
    busy_retries: int = 8
    busy_backoff_s: float = 0.05  # doubles after each busy answer, capped below
    busy_backoff_max_s: float = 1.0
    transfer_retries: int = 2  # re-issues of an operation whose data phase stopped early
    status_polls: int = 50  # Get Device Status polls after a cancel before giving up
    read_chunk: int = 64 * 1024  # a multiple of every bulk wMaxPacketSize (64, 512, 1024)

    def __post_init__(self) -> None:
        if self.timeout_ms <= 0 or self.event_poll_ms <= 0 or self.capture_timeout_s <= 0:
            raise BadInputError("PTP config: timeouts must be positive")
        if self.busy_retries < 0 or self.transfer_retries < 0 or self.status_polls < 1:
            raise BadInputError("PTP config: retry counts must be >= 0 (status_polls >= 1)")
        if self.read_chunk <= 0 or self.read_chunk % 1024:
            raise BadInputError(f"PTP config: read_chunk must be a positive multiple of 1024, got {self.read_chunk}")


@dataclass(frozen=True)
class CapturedObject(CapturedFrame):
    handle: int = 0
    format_code: int = ObjectFormat.Undefined


class _StoppedEarly(Exception):
    """A data phase stopped arriving before its declared length (internal; never escapes)."""

    def __init__(self, transaction_id: int, got: int, length: int) -> None:
        super().__init__(f"{got} of {length} bytes")
        self.transaction_id, self.got, self.length = transaction_id, got, length


class PtpCamera:
    """A PTP camera reached through one transport; satisfies the `Camera` protocol."""

    def __init__(self, transport: PtpTransport, config: PtpConfig | None = None) -> None:
        self.transport = transport
        self.config = config or PtpConfig()
        self.device_info: DeviceInfo | None = None
        self._next_tid = 0
        self._session_open = False
        self._descs: dict[int, DevicePropDesc] = {}

    def __enter__(self) -> "PtpCamera":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- session ---------------------------------------------------------------------------
    def connect(self) -> None:
        """Open a session (transaction id 0) and read DeviceInfo; a no-op when already open."""
        if self._session_open:
            return
        try:
            self._open_session()
        except SessionAlreadyOpenError:
            # A previous process died with the session open: the class Device Reset closes it.
            log.warning("%s: session already open, resetting the device", self.transport.description)
            self.transport.reset(self.config.timeout_ms)
            self._open_session()
        self.device_info = decode_device_info(self._transaction(OperationCode.GetDeviceInfo)[1])

    def _open_session(self) -> None:
        self._transaction(OperationCode.OpenSession, (SESSION_ID,))
        self._session_open = True

    def close(self) -> None:
        """Close the session and release the device; a camera already unplugged is not an error here."""
        try:
            if self._session_open:
                self._transaction(OperationCode.CloseSession)
        except DeviceDisconnectedError:
            log.warning("%s: gone before CloseSession", self.transport.description)
        finally:
            self._session_open = False
            self.transport.close()

    def describe(self) -> dict[str, str]:
        info = self.device_info or DeviceInfo()
        return {
            "protocol": "ptp",
            "manufacturer": info.manufacturer,
            "model": info.model,
            "serial": info.serial_number,
            "version": info.device_version,
        }

    # -- properties ------------------------------------------------------------------------
    def prop_desc(self, code: int) -> DevicePropDesc:
        if code not in self._descs:
            self._descs[code] = decode_prop_desc(self._transaction(OperationCode.GetDevicePropDesc, (code,))[1])
        return self._descs[code]

    def get_prop_value(self, code: int) -> PropValue:
        data = self._transaction(OperationCode.GetDevicePropValue, (code,))[1]
        return decode_value(self.prop_desc(code).data_type, data, f"value of property 0x{code:04X}")

    def set_prop_value(self, code: int, value: PropValue) -> None:
        payload = encode_value(self.prop_desc(code).data_type, value)
        self._transaction(OperationCode.SetDevicePropValue, (code,), data_out=payload)

    def _writable(self, code: int, what: str) -> DevicePropDesc:
        desc = self.prop_desc(code)
        if not desc.writable:
            # Typical cause: the mode dial is on an automatic mode, where the camera owns this setting.
            raise DeviceError(f"{self.transport.description} does not let the host set {what}; put the camera in manual (M) mode")
        return desc

    def set_exposure(self, seconds: float) -> float:
        """Set ExposureTime; returns the time the camera will really use (its nearest allowed step)."""
        if not (math.isfinite(seconds) and seconds > 0):
            raise BadInputError(f"exposure must be a positive number of seconds, got {seconds}")
        desc = self._writable(DevicePropCode.ExposureTime, "exposure time")
        value = _nearest_exposure(desc, seconds)
        self.set_prop_value(DevicePropCode.ExposureTime, value)
        return value / EXPOSURE_UNITS_PER_S

    def exposure(self) -> float:
        return int(self.get_prop_value(DevicePropCode.ExposureTime)) / EXPOSURE_UNITS_PER_S  # type: ignore[arg-type]

    def set_iso(self, iso: int) -> int:
        """Set ExposureIndex; ISO must be one the camera offers exactly (no silent rounding of gain)."""
        desc = self._writable(DevicePropCode.ExposureIndex, "ISO")
        if not desc.allows(iso):
            offered = desc.enumeration or (desc.range and f"{desc.range.minimum}..{desc.range.maximum}")
            raise BadInputError(f"ISO {iso} is not offered by {self.transport.description}; it offers {offered}")
        self.set_prop_value(DevicePropCode.ExposureIndex, iso)
        return iso

    def iso(self) -> int:
        return int(self.get_prop_value(DevicePropCode.ExposureIndex))  # type: ignore[arg-type]

    # -- objects and capture -----------------------------------------------------------------
    def object_handles(self) -> tuple[int, ...]:
        data = self._transaction(OperationCode.GetObjectHandles, (U32_MAX, 0, 0))[1]
        return decode_value(DataType.AUINT32, data, "object handle array")  # type: ignore[return-value]

    def object_info(self, handle: int) -> ObjectInfo:
        return decode_object_info(self._transaction(OperationCode.GetObjectInfo, (handle,))[1])

    def get_object(self, handle: int) -> bytes:
        return self._transaction(OperationCode.GetObject, (handle,))[1]

    def delete_object(self, handle: int) -> None:
        self._transaction(OperationCode.DeleteObject, (handle, 0))

    def capture(self) -> CapturedObject:
        """InitiateCapture, wait for the new object, download it, and delete it from the camera."""
        return self.download(self.trigger())

    def trigger(self) -> int:
        """Expose now and return the new object's handle once the camera has stored it.

        Split from `download` so a scan can start the next turntable move while this frame
        is still being transferred.
        """
        before = set(self.object_handles())
        tid = self._transaction(OperationCode.InitiateCapture, (0, 0))[0].transaction_id
        return self._await_capture(tid, before)

    def download(self, handle: int) -> CapturedObject:
        """GetObjectInfo, GetObject (size checked against the info), then DeleteObject."""
        info = self.object_info(handle)
        data = self.get_object(handle)
        if info.object_compressed_size not in (len(data), U32_MAX):
            raise PtpProtocolError(
                f"{self.transport.description}: object 0x{handle:08X} is {len(data)} bytes, ObjectInfo said {info.object_compressed_size}"
            )
        self.delete_object(handle)
        name = FORMAT_NAMES.get(info.object_format, "undefined")  # type: ignore[call-overload]
        return CapturedObject(info.filename, name, data, handle, info.object_format)

    def _await_capture(self, tid: int, before: set[int]) -> int:
        start = time.monotonic()
        deadline = start + self.config.capture_timeout_s
        added: list[int] = []
        while (now := time.monotonic()) < deadline:
            raw = self.transport.read_event(max(1, min(self.config.event_poll_ms, int((deadline - now) * 1000))))
            if raw is None:
                continue
            try:
                event = decode_container(raw)
            except PtpProtocolError as e:
                log.warning("%s: ignoring a garbled event (%s)", self.transport.description, e)
                continue
            if event.type != ContainerType.EVENT or event.transaction_id not in (tid, U32_MAX):
                continue
            if event.code == EventCode.ObjectAdded and event.params and event.params[0] not in before:
                added.append(event.params[0])
                deadline = min(deadline, time.monotonic() + self.config.complete_grace_s)
            elif event.code == EventCode.CaptureComplete:
                break
            elif event.code == EventCode.StoreFull:
                raise StoreFullError(f"{self.transport.description}: storage full during capture", ResponseCode.StoreFull)
        if added:
            return added[0]
        new = sorted(set(self.object_handles()) - before)
        if not new:
            raise CaptureTimeoutError(
                f"{self.transport.description}: no new object after InitiateCapture (transaction {tid}) "
                f"within {time.monotonic() - start:.1f} s (capture timeout {self.config.capture_timeout_s} s)"
            )
        log.warning("%s: ObjectAdded never arrived; found object 0x%08X by GetObjectHandles", self.transport.description, new[0])
        return new[0]

    # -- transactions ----------------------------------------------------------------------
    def _transaction(self, op: int, params: tuple[int, ...] = (), data_out: bytes | None = None) -> tuple[Container, bytes]:
        """One operation: command, optional data phase, response; retries DeviceBusy and truncated reads."""
        cfg = self.config
        delay, busy, truncated = cfg.busy_backoff_s, 0, 0
        while True:
            try:
                return self._exchange(op, params, data_out)
            except DeviceBusyError as e:
                busy += 1
                if busy > cfg.busy_retries:
                    raise DeviceBusyError(
                        f"{self.transport.description} stayed busy through {busy} tries of {code_name(OperationCode, op)}",
                        e.code,
                        op,
                    ) from e
                time.sleep(delay)
                delay = min(2 * delay, cfg.busy_backoff_max_s)
            except _StoppedEarly as e:
                self._cancel(e.transaction_id)
                truncated += 1
                if truncated > cfg.transfer_retries:
                    raise IncompleteTransferError(
                        f"{self.transport.description}: {code_name(OperationCode, op)} data stopped after {e.got} of "
                        f"{e.length} bytes, {truncated} times (cancelled and re-requested each time)",
                        ResponseCode.IncompleteTransfer,
                        op,
                    ) from None
                log.warning("%s: %s data stopped after %d of %d bytes; re-requesting", self.transport.description, code_name(OperationCode, op), e.got, e.length)

    def _exchange(self, op: int, params: tuple[int, ...], data_out: bytes | None) -> tuple[Container, bytes]:
        tid = 0 if op == OperationCode.OpenSession else self._next_tid  # "OpenSession uses TransactionID 0"
        self._next_tid = (tid + 1) % U32_MAX  # 0xFFFFFFFF is reserved ("all")
        what = f"{code_name(OperationCode, op)} (transaction {tid})"
        try:
            self.transport.write(encode_container(Container(ContainerType.COMMAND, op, tid, params)), self.config.timeout_ms)
            if data_out is not None:
                self.transport.write(encode_container(Container(ContainerType.DATA, op, tid, payload=data_out)), self.config.timeout_ms)
        except DeviceDisconnectedError as e:
            raise DeviceDisconnectedError(f"{what} could not be sent: {e}") from e
        first = self._read_first(what)
        head = decode_header(first)
        data = b""
        if head.type == ContainerType.DATA:
            data = self._read_data(first, head, op, tid, what)
            first = self._read_first(what)
            head = decode_header(first)
        response = decode_container(first)
        if response.type != ContainerType.RESPONSE or response.transaction_id != tid:
            raise PtpProtocolError(
                f"{self.transport.description}: expected the response to {what}, got a {head.type.name.lower()} "
                f"container 0x{head.code:04X} for transaction {head.transaction_id}"
            )
        if response.code != ResponseCode.OK:
            raise response_error(response.code, op, tid)
        return response, data

    def _read_first(self, what: str) -> bytes:
        # A zero-length packet may end a data phase whose length is a multiple of the packet size.
        for _ in range(2):
            try:
                chunk = self.transport.read(self.config.read_chunk, self.config.timeout_ms)
            except DeviceTimeoutError as e:
                raise DeviceTimeoutError(f"{self.transport.description} did not answer {what} within {self.config.timeout_ms} ms") from e
            except DeviceDisconnectedError as e:
                raise DeviceDisconnectedError(f"{what} interrupted before its answer: {e}") from e
            if chunk:
                return chunk
        raise PtpProtocolError(f"{self.transport.description}: only empty packets in answer to {what}")

    def _read_data(self, first: bytes, head: ContainerHeader, op: int, tid: int, what: str) -> bytes:
        """Collect a data phase across as many bulk reads as it takes to reach its declared length."""
        if head.code != op or head.transaction_id != tid:
            raise PtpProtocolError(f"{self.transport.description}: data container for 0x{head.code:04X}/{head.transaction_id} during {what}")
        if len(first) > head.length:
            raise PtpProtocolError(f"{self.transport.description}: {what} sent {len(first)} bytes in a {head.length}-byte container")
        parts, got, empty = [first], len(first), 0
        while got < head.length:
            try:
                chunk = self.transport.read(min(self.config.read_chunk, head.length - got), self.config.timeout_ms)
            except DeviceTimeoutError:
                raise _StoppedEarly(tid, got, head.length) from None
            except DeviceDisconnectedError as e:
                raise DeviceDisconnectedError(f"{what} interrupted after {got} of {head.length} bytes: {e}") from e
            empty = 0 if chunk else empty + 1
            if empty > 2:  # zero-length packets only: the phase ended short
                raise _StoppedEarly(tid, got, head.length)
            parts.append(chunk)
            got += len(chunk)
        if got > head.length:
            raise PtpProtocolError(f"{self.transport.description}: {what} overran its {head.length}-byte container")
        return b"".join(parts)[HEADER_SIZE:]

    def _cancel(self, tid: int) -> None:
        """USB Still Image Class cancel: request, then poll device status until the camera is idle again."""
        timeout = self.config.timeout_ms
        self.transport.cancel(tid, timeout)
        for _ in range(self.config.status_polls):
            code, halted = self.transport.get_status(timeout)
            for endpoint in halted:
                self.transport.clear_halt(endpoint)
            if code == ResponseCode.OK:
                return
            time.sleep(0.01)
        raise DeviceError(f"{self.transport.description} still not idle after cancelling transaction {tid}")


def _nearest_exposure(desc: DevicePropDesc, seconds: float) -> int:
    """The camera value for `seconds`: the nearest offered step, refused if more than 1/6 stop away."""
    wanted = seconds * EXPOSURE_UNITS_PER_S
    if desc.enumeration:
        candidates = [int(v) for v in desc.enumeration if int(v) > 0]  # type: ignore[call-overload]
    elif desc.range is not None:
        r = desc.range
        step = max(r.step, 1)
        snapped = r.minimum + step * round((wanted - r.minimum) / step)
        candidates = [min(max(snapped, r.minimum), r.maximum)]
    else:
        candidates = [max(1, round(wanted))]
    best = min(candidates, key=lambda v: abs(math.log2(v / wanted)) if v > 0 else math.inf)
    if best <= 0 or abs(math.log2(best / wanted)) > 1 / 6:
        raise BadInputError(f"exposure {seconds} s is not available on this camera (nearest {best / EXPOSURE_UNITS_PER_S} s)")
    return best


def open_ptp_camera(
    backend: object = None,
    vendor: int | None = None,
    product: int | None = None,
    timeout_ms: int = 5000,
    config: PtpConfig | None = None,
) -> PtpCamera:
    """Find the first USB PTP camera (None = pyusb's default libusb backend), open a session, return it."""
    transport = UsbPtpTransport.find(backend=backend, vendor=vendor, product=product)
    camera = PtpCamera(transport, config or PtpConfig(timeout_ms=timeout_ms))
    try:
        camera.connect()
    except BaseException:
        transport.close()
        raise
    return camera
