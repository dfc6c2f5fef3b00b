"""The PTP wire codec: containers and datasets round-trip, and broken bytes become typed errors."""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from station.capture.ptp_codec import (
    Container,
    ContainerType,
    DataType,
    DeviceBusyError,
    DeviceInfo,
    DevicePropCode,
    DevicePropDesc,
    EventCode,
    ObjectFormat,
    ObjectInfo,
    OperationCode,
    PropRange,
    PtpProtocolError,
    PtpResponseError,
    ResponseCode,
    SessionAlreadyOpenError,
    decode_container,
    decode_device_info,
    decode_header,
    decode_object_info,
    decode_prop_desc,
    decode_value,
    encode_container,
    encode_device_info,
    encode_object_info,
    encode_prop_desc,
    encode_value,
    pack_string,
    response_error,
)
from station.errors import BadInputError, DeviceError

pytestmark = pytest.mark.no_kernels

u32 = st.integers(0, 0xFFFFFFFF)
ptp_text = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=60)

DEVICE_INFO = DeviceInfo(
    standard_version=110,
    vendor_extension_id=6,
    vendor_extension_version=100,
    vendor_extension_desc="microsoft.com: 1.0",
    operations_supported=tuple(OperationCode),
    events_supported=(EventCode.ObjectAdded, EventCode.CaptureComplete),
    device_properties_supported=(DevicePropCode.ExposureTime, DevicePropCode.ExposureIndex),
    capture_formats=(ObjectFormat.DNG,),
    image_formats=(ObjectFormat.DNG, ObjectFormat.EXIF_JPEG),
    manufacturer="Stône Optics",
    model="Model 石 7",
    device_version="2.1",
    serial_number="0042",
)


def test_command_container_layout_is_length_type_code_tid_then_params():
    raw = encode_container(Container(ContainerType.COMMAND, OperationCode.OpenSession, 0, (1,)))
    assert raw == struct.pack("<IHHII", 16, 1, 0x1002, 0, 1)


@given(
    kind=st.sampled_from([ContainerType.COMMAND, ContainerType.RESPONSE, ContainerType.EVENT]),
    code=st.integers(0, 0xFFFF),
    tid=u32,
    params=st.lists(u32, max_size=5),
)
@settings(max_examples=200, deadline=None)
def test_parameter_containers_round_trip(kind, code, tid, params):
    container = Container(kind, code, tid, tuple(params))
    assert decode_container(encode_container(container)) == container


@given(tid=u32, payload=st.binary(max_size=2000))
@settings(max_examples=100, deadline=None)
def test_data_containers_round_trip(tid, payload):
    container = Container(ContainerType.DATA, OperationCode.GetObject, tid, payload=payload)
    raw = encode_container(container)
    assert decode_header(raw).length == len(raw) == 12 + len(payload)
    assert decode_container(raw) == container


def test_encoding_refuses_six_parameters_and_non_u32_values():
    with pytest.raises(BadInputError, match="at most 5"):
        encode_container(Container(ContainerType.COMMAND, 0x1001, 0, (0,) * 6))
    with pytest.raises(BadInputError, match="u32"):
        encode_container(Container(ContainerType.COMMAND, 0x1001, 0, (2**32,)))


@pytest.mark.parametrize(
    "raw, message",
    [
        (b"\x0c\x00\x00", "truncated"),
        (struct.pack("<IHHI", 8, 3, 0x2001, 0), "below the 12-byte header"),
        (struct.pack("<IHHI", 12, 9, 0x2001, 0), "unknown type 9"),
        (struct.pack("<IHHI", 14, 3, 0x2001, 0) + b"\x00\x00", "not 12 \\+ 4\\*n"),
        (struct.pack("<IHHI", 36, 3, 0x2001, 0) + bytes(24), "exceeds 5 parameters"),
        (struct.pack("<IHHI", 20, 3, 0x2001, 0) + bytes(4), "declares 20 bytes but 16 arrived"),
    ],
)
def test_malformed_containers_raise_protocol_errors(raw, message):
    with pytest.raises(PtpProtocolError, match=message):
        decode_container(raw)


@given(st.binary(max_size=64))
@settings(max_examples=300, deadline=None)
def test_garbage_bytes_never_escape_as_anything_but_protocol_errors(raw):
    for decode in (decode_container, decode_device_info, decode_object_info, decode_prop_desc):
        try:
            decode(raw)
        except PtpProtocolError:
            pass


def test_protocol_errors_are_device_errors_with_exit_code_3():
    with pytest.raises(DeviceError) as caught:
        decode_container(b"garbage")
    assert caught.value.exit_code == 3


def test_ptp_string_is_count_of_utf16_units_including_nul():
    assert pack_string("") == b"\x00"
    assert pack_string("AB") == b"\x03A\x00B\x00\x00\x00"
    assert decode_value(DataType.STR, b"\x03A\x00B\x00\x00\x00") == "AB"


def test_ptp_string_without_terminator_or_too_long_is_refused():
    with pytest.raises(PtpProtocolError, match="NUL terminator"):
        decode_value(DataType.STR, b"\x02A\x00B\x00")
    with pytest.raises(BadInputError, match="too long"):
        pack_string("x" * 255)


@given(manufacturer=ptp_text, model=ptp_text, ops=st.lists(st.integers(0, 0xFFFF), max_size=40))
@settings(max_examples=100, deadline=None)
def test_device_info_round_trips(manufacturer, model, ops):
    info = DeviceInfo(manufacturer=manufacturer, model=model, operations_supported=tuple(ops))
    assert decode_device_info(encode_device_info(info)) == info


def test_device_info_truncated_anywhere_raises_protocol_error():
    raw = encode_device_info(DEVICE_INFO)
    assert decode_device_info(raw) == DEVICE_INFO
    for cut in range(len(raw)):
        with pytest.raises(PtpProtocolError, match="DeviceInfo dataset"):
            decode_device_info(raw[:cut])


def test_object_info_round_trips_with_unicode_filename():
    info = ObjectInfo(
        storage_id=0x00010001,
        object_format=ObjectFormat.DNG,
        object_compressed_size=123_456_789,
        image_pix_width=6000,
        image_pix_height=4000,
        image_bit_depth=16,
        sequence_number=7,
        filename="stein_é_石.DNG",
        capture_date="20260101T120000.0Z",
    )
    assert decode_object_info(encode_object_info(info)) == info


def test_array_claiming_more_elements_than_bytes_is_refused_before_allocating():
    raw = struct.pack("<I", 0xFFFFFFFF) + bytes(8)
    with pytest.raises(PtpProtocolError, match="runs past the end"):
        decode_value(DataType.AUINT32, raw)


@pytest.mark.parametrize(
    "desc",
    [
        DevicePropDesc(0x500D, DataType.UINT32, True, 333, 80, range=PropRange(1, 300_000, 1)),
        DevicePropDesc(0x500F, DataType.UINT16, True, 100, 400, enumeration=(100, 200, 400, 800)),
        DevicePropDesc(0x5001, DataType.UINT8, False, 100, 57),
        DevicePropDesc(0xD001, DataType.STR, True, "", "Läb", enumeration=("", "Läb", "Studio")),
        DevicePropDesc(0xD002, DataType.AUINT16, True, (), (1, 2, 3)),
    ],
)
def test_device_prop_desc_round_trips_in_every_form(desc):
    assert decode_prop_desc(encode_prop_desc(desc)) == desc


def test_device_prop_desc_with_unknown_form_flag_is_refused():
    desc = DevicePropDesc(0x500F, DataType.UINT16, True, 100, 100)
    raw = encode_prop_desc(desc)[:-1] + b"\x07"
    with pytest.raises(PtpProtocolError, match="unknown form flag 7"):
        decode_prop_desc(raw)


def test_prop_desc_allows_only_values_on_its_range_grid_or_enumeration():
    ranged = DevicePropDesc(0x500D, DataType.UINT32, True, 10, 10, range=PropRange(10, 100, 10))
    assert ranged.allows(40) and not ranged.allows(45) and not ranged.allows(110)
    listed = DevicePropDesc(0x500F, DataType.UINT16, True, 100, 100, enumeration=(100, 200))
    assert listed.allows(200) and not listed.allows(150)


def test_value_that_does_not_fit_its_data_type_is_refused():
    with pytest.raises(BadInputError, match="does not fit"):
        encode_value(DataType.UINT16, 70_000)


def test_response_codes_map_to_typed_exceptions_naming_code_and_operation():
    busy = response_error(ResponseCode.DeviceBusy, OperationCode.InitiateCapture, 5)
    assert isinstance(busy, DeviceBusyError) and isinstance(busy, DeviceError)
    assert busy.code == 0x2019 and busy.exit_code == 3
    assert str(busy) == "camera answered DeviceBusy (0x2019) to InitiateCapture (0x100E) (transaction 5)"
    assert isinstance(response_error(ResponseCode.SessionAlreadyOpened), SessionAlreadyOpenError)
    vendor = response_error(0xA001, 0x9128)
    assert type(vendor) is PtpResponseError and "0xA001" in str(vendor) and "0x9128" in str(vendor)
