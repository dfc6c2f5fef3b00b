"""PTP (ISO 15740) wire format: containers, datasets, codes, and response codes as typed errors.

Pure functions over bytes, no I/O, so the driver and the simulated camera share one codec and
tests can round-trip and fuzz it. Comments quote the PIMA 15740 / USB Still Image Class layout
being packed. Everything is little-endian.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from enum import IntEnum
from typing import Union

from station.errors import BadInputError, DeviceError

# "Generic container: u32 ContainerLength, u16 ContainerType, u16 Code, u32 TransactionID, payload"
HEADER = struct.Struct("<IHHI")
HEADER_SIZE = HEADER.size
MAX_PARAMS = 5
U32_MAX = 0xFFFFFFFF


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


class OperationCode(IntEnum):
    GetDeviceInfo = 0x1001
    OpenSession = 0x1002
    CloseSession = 0x1003
    GetStorageIDs = 0x1004
    GetObjectHandles = 0x1007
    GetObjectInfo = 0x1008
    GetObject = 0x1009
    DeleteObject = 0x100B
    InitiateCapture = 0x100E
    GetDevicePropDesc = 0x1014
    GetDevicePropValue = 0x1015
    SetDevicePropValue = 0x1016
    GetPartialObject = 0x101B


class ResponseCode(IntEnum):
    OK = 0x2001
    GeneralError = 0x2002
    SessionNotOpen = 0x2003
    InvalidTransactionID = 0x2004
    OperationNotSupported = 0x2005
    ParameterNotSupported = 0x2006
    IncompleteTransfer = 0x2007
    InvalidStorageID = 0x2008
    InvalidObjectHandle = 0x2009
    DevicePropNotSupported = 0x200A
    InvalidObjectFormatCode = 0x200B
    StoreFull = 0x200C
    AccessDenied = 0x200F
    DeviceBusy = 0x2019
    InvalidDevicePropValue = 0x201C
    InvalidParameter = 0x201D
    SessionAlreadyOpened = 0x201E
    TransactionCancelled = 0x201F


class EventCode(IntEnum):
    CancelTransaction = 0x4001
    ObjectAdded = 0x4002
    DevicePropChanged = 0x4006
    StoreFull = 0x400A
    CaptureComplete = 0x400D


class ObjectFormat(IntEnum):
    Undefined = 0x3000
    EXIF_JPEG = 0x3801
    TIFF = 0x380D
    DNG = 0x3811


class DevicePropCode(IntEnum):
    BatteryLevel = 0x5001
    ExposureTime = 0x500D  # u32, units of 0.1 ms
    ExposureIndex = 0x500F  # u16, ISO speed


class DataType(IntEnum):
    INT8 = 0x0001
    UINT8 = 0x0002
    INT16 = 0x0003
    UINT16 = 0x0004
    INT32 = 0x0005
    UINT32 = 0x0006
    INT64 = 0x0007
    UINT64 = 0x0008
    AUINT16 = 0x4004
    AUINT32 = 0x4006
    STR = 0xFFFF


# "Arrays: u32 NumElements followed by the elements"; array types are 0x4000 | element type.
_SCALAR_FORMAT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "q", 8: "Q"}
PropValue = Union[int, str, tuple[int, ...]]


class PtpProtocolError(DeviceError):
    """The camera sent bytes that are not a well-formed PTP container or dataset."""


class PtpResponseError(DeviceError):
    """The camera answered an operation with a response code other than OK."""

    def __init__(self, message: str, code: int, operation: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.operation = operation


class GeneralPtpError(PtpResponseError): ...
class SessionNotOpenError(PtpResponseError): ...
class InvalidTransactionIdError(PtpResponseError): ...
class OperationNotSupportedError(PtpResponseError): ...
class IncompleteTransferError(PtpResponseError): ...
class InvalidObjectHandleError(PtpResponseError): ...
class DevicePropNotSupportedError(PtpResponseError): ...
class StoreFullError(PtpResponseError): ...
class AccessDeniedError(PtpResponseError): ...
class DeviceBusyError(PtpResponseError): ...
class InvalidDevicePropValueError(PtpResponseError): ...
class InvalidParameterError(PtpResponseError): ...
class SessionAlreadyOpenError(PtpResponseError): ...
class TransactionCancelledError(PtpResponseError): ...


RESPONSE_ERRORS: dict[int, type[PtpResponseError]] = {
    ResponseCode.GeneralError: GeneralPtpError,
    ResponseCode.SessionNotOpen: SessionNotOpenError,
    ResponseCode.InvalidTransactionID: InvalidTransactionIdError,
    ResponseCode.OperationNotSupported: OperationNotSupportedError,
    ResponseCode.ParameterNotSupported: InvalidParameterError,
    ResponseCode.IncompleteTransfer: IncompleteTransferError,
    ResponseCode.InvalidObjectHandle: InvalidObjectHandleError,
    ResponseCode.DevicePropNotSupported: DevicePropNotSupportedError,
    ResponseCode.StoreFull: StoreFullError,
    ResponseCode.AccessDenied: AccessDeniedError,
    ResponseCode.DeviceBusy: DeviceBusyError,
    ResponseCode.InvalidDevicePropValue: InvalidDevicePropValueError,
    ResponseCode.InvalidParameter: InvalidParameterError,
    ResponseCode.SessionAlreadyOpened: SessionAlreadyOpenError,
    ResponseCode.TransactionCancelled: TransactionCancelledError,
}


def code_name(enum: type[IntEnum], code: int) -> str:
    """`DeviceBusy (0x2019)`, or just the hex for vendor codes, for messages operators can search."""
    try:
        return f"{enum(code).name} (0x{code:04X})"
    except ValueError:
        return f"0x{code:04X}"


def response_error(code: int, operation: int | None = None, transaction_id: int | None = None) -> PtpResponseError:
    """The typed exception for a non-OK response code (the way rawpy maps LibRaw codes)."""
    where = "" if operation is None else f" to {code_name(OperationCode, operation)}"
    tid = "" if transaction_id is None else f" (transaction {transaction_id})"
    cls = RESPONSE_ERRORS.get(code, PtpResponseError)
    return cls(f"camera answered {code_name(ResponseCode, code)}{where}{tid}", code, operation)


@dataclass(frozen=True)
class Container:
    type: ContainerType
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    payload: bytes = b""


@dataclass(frozen=True)
class ContainerHeader:
    length: int
    type: ContainerType
    code: int
    transaction_id: int


def encode_container(container: Container) -> bytes:
    """Pack a container; data containers carry a payload, the others up to five u32 parameters."""
    if container.type == ContainerType.DATA:
        if container.params:
            raise BadInputError("PTP data container cannot carry parameters")
        body = bytes(container.payload)
    else:
        if container.payload:
            raise BadInputError(f"PTP {container.type.name.lower()} container cannot carry a payload")
        if len(container.params) > MAX_PARAMS:
            raise BadInputError(f"PTP container takes at most {MAX_PARAMS} parameters, got {len(container.params)}")
        if any(not 0 <= p <= U32_MAX for p in container.params):
            raise BadInputError(f"PTP parameters must be u32, got {container.params}")
        body = struct.pack(f"<{len(container.params)}I", *container.params)
    length = HEADER_SIZE + len(body)
    return HEADER.pack(length, container.type, container.code, container.transaction_id) + body


def decode_header(buf: bytes) -> ContainerHeader:
    """Read the 12-byte header of the first transfer of a phase; the rest may still be in flight."""
    if len(buf) < HEADER_SIZE:
        raise PtpProtocolError(f"PTP container truncated: {len(buf)} bytes, a header needs {HEADER_SIZE}")
    length, ctype, code, tid = HEADER.unpack_from(buf)
    if length < HEADER_SIZE:
        raise PtpProtocolError(f"PTP container declares length {length}, below the {HEADER_SIZE}-byte header")
    try:
        kind = ContainerType(ctype)
    except ValueError:
        raise PtpProtocolError(f"PTP container has unknown type {ctype} (expected 1-4)") from None
    if kind != ContainerType.DATA and (length - HEADER_SIZE) % 4 != 0:
        raise PtpProtocolError(f"PTP {kind.name.lower()} container length {length} is not 12 + 4*n")
    if kind != ContainerType.DATA and length > HEADER_SIZE + 4 * MAX_PARAMS:
        raise PtpProtocolError(f"PTP {kind.name.lower()} container length {length} exceeds {MAX_PARAMS} parameters")
    return ContainerHeader(length, kind, code, tid)


def decode_container(buf: bytes) -> Container:
    """Unpack one complete container; its declared length must match the bytes given."""
    head = decode_header(buf)
    if head.length != len(buf):
        raise PtpProtocolError(f"PTP container declares {head.length} bytes but {len(buf)} arrived")
    body = bytes(buf[HEADER_SIZE:])
    if head.type == ContainerType.DATA:
        return Container(head.type, head.code, head.transaction_id, payload=body)
    params = struct.unpack(f"<{len(body) // 4}I", body)
    return Container(head.type, head.code, head.transaction_id, params=params)


class _Reader:
    """Cursor over a dataset; every short read is a PtpProtocolError naming the dataset."""

    def __init__(self, buf: bytes, what: str) -> None:
        self.buf, self.pos, self.what = bytes(buf), 0, what

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.buf):
            raise PtpProtocolError(f"{self.what} truncated at byte {self.pos}: needs {n} more, {len(self.buf) - self.pos} left")
        chunk = self.buf[self.pos : self.pos + n]
        self.pos += n
        return chunk

    def scalar(self, data_type: int) -> int:
        fmt = "<" + _SCALAR_FORMAT[data_type]
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def string(self) -> str:
        # "PTP string: u8 NumChars (including the terminating null), then UTF-16LE characters"
        count = self.scalar(DataType.UINT8)
        if count == 0:
            return ""
        raw = self.take(2 * count)
        if raw[-2:] != b"\x00\x00":
            raise PtpProtocolError(f"{self.what}: PTP string at byte {self.pos - 2 * count - 1} lacks its NUL terminator")
        try:
            return raw[:-2].decode("utf-16-le")
        except UnicodeDecodeError as e:
            raise PtpProtocolError(f"{self.what}: PTP string is not valid UTF-16LE ({e.reason})") from None

    def value(self, data_type: int) -> PropValue:
        if data_type == DataType.STR:
            return self.string()
        if data_type in _SCALAR_FORMAT:
            return self.scalar(data_type)
        if data_type & 0x4000 and (data_type & 0xFF) in _SCALAR_FORMAT:
            count = self.scalar(DataType.UINT32)
            element = data_type & 0xFF
            if count * struct.calcsize(_SCALAR_FORMAT[element]) > len(self.buf) - self.pos:
                raise PtpProtocolError(f"{self.what}: array of {count} elements runs past the end ({len(self.buf)} bytes)")
            return tuple(self.scalar(element) for _ in range(count))
        raise PtpProtocolError(f"{self.what}: unsupported PTP data type 0x{data_type:04X}")


def pack_string(text: str) -> bytes:
    if text == "":
        return b"\x00"
    raw = (text + "\x00").encode("utf-16-le")
    if len(raw) // 2 > 255:
        raise BadInputError(f"PTP string too long ({len(raw) // 2} UTF-16 units incl. NUL, max 255): {text[:40]!r}...")
    return bytes([len(raw) // 2]) + raw


def encode_value(data_type: int, value: PropValue) -> bytes:
    """Pack a property value of a PTP data type (scalar, array or string)."""
    try:
        if data_type == DataType.STR:
            return pack_string(str(value))
        if data_type in _SCALAR_FORMAT:
            return struct.pack("<" + _SCALAR_FORMAT[data_type], value)
        if data_type & 0x4000 and (data_type & 0xFF) in _SCALAR_FORMAT:
            items = tuple(value)  # type: ignore[arg-type]
            return struct.pack(f"<I{len(items)}{_SCALAR_FORMAT[data_type & 0xFF]}", len(items), *items)
    except struct.error as e:
        raise BadInputError(f"value {value!r} does not fit PTP data type 0x{data_type:04X}: {e}") from None
    raise BadInputError(f"unsupported PTP data type 0x{data_type:04X}")


def decode_value(data_type: int, buf: bytes, what: str = "property value") -> PropValue:
    return _Reader(buf, what).value(data_type)


def _encode_fields(obj: object, layout: tuple[tuple[str, int], ...]) -> bytes:
    return b"".join(encode_value(data_type, getattr(obj, name)) for name, data_type in layout)


def _decode_fields(buf: bytes, layout: tuple[tuple[str, int], ...], what: str) -> dict[str, PropValue]:
    # Trailing bytes are ignored: some cameras pad datasets or append vendor fields.
    reader = _Reader(buf, what)
    return {name: reader.value(data_type) for name, data_type in layout}


@dataclass(frozen=True)
class DeviceInfo:
    standard_version: int = 100
    vendor_extension_id: int = 0
    vendor_extension_version: int = 0
    vendor_extension_desc: str = ""
    functional_mode: int = 0
    operations_supported: tuple[int, ...] = ()
    events_supported: tuple[int, ...] = ()
    device_properties_supported: tuple[int, ...] = ()
    capture_formats: tuple[int, ...] = ()
    image_formats: tuple[int, ...] = ()
    manufacturer: str = ""
    model: str = ""
    device_version: str = ""
    serial_number: str = ""


_A16, _U16, _U32 = DataType.AUINT16, DataType.UINT16, DataType.UINT32
# ISO 15740 table 5.5.1 "DeviceInfo Dataset", in wire order.
_DEVICE_INFO_TYPES = (_U16, _U32, _U16, DataType.STR, _U16, _A16, _A16, _A16, _A16, _A16) + (DataType.STR,) * 4
DEVICE_INFO_LAYOUT = tuple(zip((f.name for f in fields(DeviceInfo)), _DEVICE_INFO_TYPES))


@dataclass(frozen=True)
class ObjectInfo:
    storage_id: int = 0
    object_format: int = ObjectFormat.Undefined
    protection_status: int = 0
    object_compressed_size: int = 0
    thumb_format: int = 0
    thumb_compressed_size: int = 0
    thumb_pix_width: int = 0
    thumb_pix_height: int = 0
    image_pix_width: int = 0
    image_pix_height: int = 0
    image_bit_depth: int = 0
    parent_object: int = 0
    association_type: int = 0
    association_desc: int = 0
    sequence_number: int = 0
    filename: str = ""
    capture_date: str = ""
    modification_date: str = ""
    keywords: str = ""


# ISO 15740 table 5.5.2 "ObjectInfo Dataset", in wire order.
_OBJECT_INFO_TYPES = (_U32, _U16, _U16, _U32, _U16) + (_U32,) * 6 + (_U32, _U16, _U32, _U32) + (DataType.STR,) * 4
OBJECT_INFO_LAYOUT = tuple(zip((f.name for f in fields(ObjectInfo)), _OBJECT_INFO_TYPES))


def encode_device_info(info: DeviceInfo) -> bytes:
    return _encode_fields(info, DEVICE_INFO_LAYOUT)


def decode_device_info(buf: bytes) -> DeviceInfo:
    return DeviceInfo(**_decode_fields(buf, DEVICE_INFO_LAYOUT, "DeviceInfo dataset"))  # type: ignore[arg-type]


def encode_object_info(info: ObjectInfo) -> bytes:
    return _encode_fields(info, OBJECT_INFO_LAYOUT)


def decode_object_info(buf: bytes) -> ObjectInfo:
    return ObjectInfo(**_decode_fields(buf, OBJECT_INFO_LAYOUT, "ObjectInfo dataset"))  # type: ignore[arg-type]


@dataclass(frozen=True)
class PropRange:
    minimum: int
    maximum: int
    step: int


@dataclass(frozen=True)
class DevicePropDesc:
    """What a property holds and which values the camera accepts (range form or enumeration form)."""

    code: int
    data_type: int
    writable: bool
    factory_default: PropValue
    current: PropValue
    range: PropRange | None = None
    enumeration: tuple[PropValue, ...] | None = None

    def allows(self, value: PropValue) -> bool:
        if self.range is not None:
            r = self.range
            return isinstance(value, int) and r.minimum <= value <= r.maximum and (value - r.minimum) % max(r.step, 1) == 0
        if self.enumeration is not None:
            return value in self.enumeration
        return True


def encode_prop_desc(desc: DevicePropDesc) -> bytes:
    # "u16 DevicePropertyCode, u16 DataType, u8 GetSet, FactoryDefaultValue, CurrentValue, u8 FormFlag, form"
    dt = desc.data_type
    out = struct.pack("<HHB", desc.code, dt, int(desc.writable))
    out += encode_value(dt, desc.factory_default) + encode_value(dt, desc.current)
    if desc.range is not None:
        r = desc.range
        return out + b"\x01" + b"".join(encode_value(dt, v) for v in (r.minimum, r.maximum, r.step))
    if desc.enumeration is not None:
        values = b"".join(encode_value(dt, v) for v in desc.enumeration)
        return out + b"\x02" + struct.pack("<H", len(desc.enumeration)) + values
    return out + b"\x00"


def decode_prop_desc(buf: bytes) -> DevicePropDesc:
    reader = _Reader(buf, "DevicePropDesc dataset")
    code, dt = reader.scalar(DataType.UINT16), reader.scalar(DataType.UINT16)
    get_set = reader.scalar(DataType.UINT8)
    default, current = reader.value(dt), reader.value(dt)
    form = reader.scalar(DataType.UINT8)
    if form == 0:
        return DevicePropDesc(code, dt, bool(get_set), default, current)
    if form == 1:
        lo, hi, step = (reader.value(dt) for _ in range(3))
        return DevicePropDesc(code, dt, bool(get_set), default, current, range=PropRange(lo, hi, step))  # type: ignore[arg-type]
    if form == 2:
        count = reader.scalar(DataType.UINT16)
        values = tuple(reader.value(dt) for _ in range(count))
        return DevicePropDesc(code, dt, bool(get_set), default, current, enumeration=values)
    raise PtpProtocolError(f"DevicePropDesc for 0x{code:04X}: unknown form flag {form} (expected 0, 1 or 2)")
