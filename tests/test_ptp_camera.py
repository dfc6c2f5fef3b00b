"""The PTP driver against the simulated camera, through pyusb's real API and a simulated backend."""

import logging
import random
from dataclasses import replace

import pytest
import usb.backend.libusb1
import usb.core
import usb.util

from sim.ptp_camera import CaptureSettings, PtpFaults, SimPtpCamera
from sim.usb_backend import SimUsbBackend, SimUsbDevice, find_sim_camera
from station.capture.ptp import CaptureTimeoutError, PtpCamera, PtpConfig, open_ptp_camera
from station.capture.ptp_codec import (
    Container,
    ContainerType,
    DevicePropCode,
    DeviceBusyError,
    IncompleteTransferError,
    InvalidDevicePropValueError,
    ObjectFormat,
    OperationCode,
    PtpProtocolError,
    ResponseCode,
    StoreFullError,
    decode_container,
    encode_container,
)
from station.capture.transport import CameraNotFoundError
from station.errors import BadInputError, DeviceDisconnectedError, DeviceError

pytestmark = pytest.mark.no_kernels

FRAME = random.Random(15740).randbytes(300_000)  # spans hundreds of 512-byte packets
FAST = PtpConfig(timeout_ms=150, capture_timeout_s=2.0, event_poll_ms=20, busy_backoff_s=0.002, busy_backoff_max_s=0.01)


class FrameRecorder:
    """A frame source that returns fixed bytes and remembers the settings of every shot."""

    def __init__(self) -> None:
        self.shots: list[CaptureSettings] = []

    def __call__(self, settings: CaptureSettings) -> tuple[bytes, str]:
        self.shots.append(settings)
        return FRAME, f"IMG_{len(self.shots):04d}.DNG"


def make_rig(config: PtpConfig = FAST, **sim_options) -> tuple[SimPtpCamera, PtpCamera, FrameRecorder]:
    source = FrameRecorder()
    sim = SimPtpCamera(source, time_scale=0.05, **sim_options)
    return sim, open_ptp_camera(backend=SimUsbBackend(sim), config=config), source


def ops(sim: SimPtpCamera) -> list[int]:
    return [op for op, _tid in sim.operations]


def test_sim_camera_is_an_ordinary_pyusb_device_with_a_ptp_interface():
    device = find_sim_camera(SimPtpCamera(FrameRecorder()))
    device.set_configuration()
    intf = usb.util.find_descriptor(device.get_active_configuration(), bInterfaceClass=6)
    assert (intf.bInterfaceSubClass, intf.bInterfaceProtocol) == (1, 1)
    kinds = sorted((usb.util.endpoint_direction(e.bEndpointAddress), usb.util.endpoint_type(e.bmAttributes)) for e in intf)
    assert kinds == [(usb.util.ENDPOINT_OUT, 2), (usb.util.ENDPOINT_IN, 2), (usb.util.ENDPOINT_IN, 3)]


def test_sim_answers_raw_pyusb_transfers_and_checks_transaction_ids():
    device = find_sim_camera(SimPtpCamera(FrameRecorder()))
    device.set_configuration()

    def exchange(op: int, tid: int, *params: int) -> Container:
        device.write(0x01, encode_container(Container(ContainerType.COMMAND, op, tid, params)))
        return decode_container(device.read(0x82, 512).tobytes())

    assert exchange(OperationCode.GetObjectHandles, 0, 0xFFFFFFFF).code == ResponseCode.SessionNotOpen
    assert exchange(OperationCode.OpenSession, 0, 1).code == ResponseCode.OK
    assert exchange(OperationCode.CloseSession, 5).code == ResponseCode.InvalidTransactionID
    assert exchange(OperationCode.CloseSession, 1).code == ResponseCode.OK  # a refused id is not consumed


def test_capture_downloads_the_whole_object_then_deletes_it_from_the_camera():
    sim, camera, _ = make_rig()
    frame = camera.capture()
    assert (frame.filename, frame.format, frame.format_code) == ("IMG_0001.DNG", "dng", ObjectFormat.DNG)
    assert frame.data == FRAME
    assert sim.objects == {}
    flow = ops(sim)[ops(sim).index(OperationCode.InitiateCapture) :]
    assert flow == [OperationCode.InitiateCapture, OperationCode.GetObjectInfo, OperationCode.GetObject, OperationCode.DeleteObject]
    camera.close()
    assert sim.session_id is None


def test_open_session_uses_transaction_zero_and_later_ids_increment():
    sim, camera, _ = make_rig()
    camera.capture()
    tids = [tid for _op, tid in sim.operations]
    assert sim.operations[0] == (OperationCode.OpenSession, 0)
    assert tids == list(range(len(tids)))
    assert camera.describe()["model"] == "Sim PTP Camera"


def test_exposure_and_iso_reach_the_camera_and_the_shot():
    sim, camera, source = make_rig()
    assert camera.set_exposure(1 / 60) == pytest.approx(0.0167)
    assert camera.set_iso(400) == 400
    assert (camera.exposure(), camera.iso()) == (pytest.approx(0.0167), 400)
    assert sim.props[DevicePropCode.ExposureTime].current == 167  # 0.1 ms units
    camera.capture()
    assert source.shots == [CaptureSettings(exposure_s=0.0167, iso=400)]


def test_iso_the_camera_does_not_offer_is_refused_listing_what_it_offers():
    _, camera, _ = make_rig()
    with pytest.raises(BadInputError, match=r"ISO 150 .* offers \(100, 200, 400"):
        camera.set_iso(150)


@pytest.mark.parametrize("seconds", [60.0, -1.0, 0.0, float("nan"), 1e-6])
def test_exposure_outside_what_the_camera_can_do_is_refused(seconds):
    _, camera, _ = make_rig()
    with pytest.raises(BadInputError, match="exposure"):
        camera.set_exposure(seconds)


def test_read_only_exposure_asks_for_manual_mode():
    sim, camera, _ = make_rig()
    sim.props[DevicePropCode.ExposureTime] = replace(sim.props[DevicePropCode.ExposureTime], writable=False)
    with pytest.raises(DeviceError, match="manual \\(M\\) mode"):
        camera.set_exposure(0.01)


def test_driver_config_with_impossible_values_is_refused():
    with pytest.raises(BadInputError, match="read_chunk"):
        PtpConfig(read_chunk=1000)


def test_camera_refusing_a_property_value_raises_a_typed_error():
    _, camera, _ = make_rig()
    with pytest.raises(InvalidDevicePropValueError, match="InvalidDevicePropValue .* SetDevicePropValue"):
        camera.set_prop_value(DevicePropCode.ExposureIndex, 150)


def test_busy_camera_is_retried_with_new_transactions_until_it_answers():
    sim, camera, _ = make_rig()
    sim.faults.busy_next = 4
    assert camera.capture().data == FRAME
    assert sim.faults.busy_next == 0
    assert ops(sim).count(OperationCode.GetObjectHandles) == 5  # four busy answers, then the real one
    tids = [tid for _op, tid in sim.operations]
    assert len(set(tids)) == len(tids)


def test_camera_busy_beyond_the_retry_budget_raises_device_busy_error():
    sim, camera, _ = make_rig(PtpConfig(**{**FAST.__dict__, "busy_retries": 3}))
    sim.faults.busy_next = 100
    with pytest.raises(DeviceBusyError, match="stayed busy through 4 tries of GetObjectHandles") as caught:
        camera.capture()
    assert caught.value.exit_code == 3 and sim.faults.busy_next == 96


def test_dropped_object_added_event_is_recovered_by_listing_object_handles(caplog):
    sim, camera, _ = make_rig(faults=PtpFaults(drop_object_added=1))
    with caplog.at_level(logging.WARNING, logger="station.capture.ptp"):
        assert camera.capture().data == FRAME
    assert "ObjectAdded never arrived" in caplog.text
    assert ops(sim).count(OperationCode.GetObjectHandles) == 2  # before the shot, and the recovery
    assert sim.objects == {}


def test_both_capture_events_dropped_is_recovered_after_the_capture_deadline():
    config = PtpConfig(**{**FAST.__dict__, "capture_timeout_s": 0.3})
    sim, camera, _ = make_rig(config, faults=PtpFaults(drop_object_added=1, drop_capture_complete=1))
    assert camera.capture().data == FRAME


def test_no_new_object_before_the_deadline_raises_capture_timeout():
    config = PtpConfig(**{**FAST.__dict__, "capture_timeout_s": 0.2})
    sim, camera, _ = make_rig(config, capture_latency_s=1e4, faults=PtpFaults(drop_object_added=1, drop_capture_complete=1))
    with pytest.raises(CaptureTimeoutError, match="no new object after InitiateCapture") as caught:
        camera.capture()
    assert isinstance(caught.value, TimeoutError) and caught.value.exit_code == 3


def test_data_phase_delivered_in_odd_small_chunks_is_reassembled():
    sim, camera, _ = make_rig(faults=PtpFaults(chunk_bytes=1000))
    assert camera.capture().data == FRAME


def test_zero_length_packet_after_a_whole_packet_data_phase_is_skipped():
    exact = FRAME[: 512 * 300 - 12]  # header + payload fill exactly 300 packets
    sim = SimPtpCamera(lambda settings: (exact, "exact.dng"), time_scale=0.05)
    with open_ptp_camera(backend=SimUsbBackend(sim), config=FAST) as camera:
        assert camera.capture().data == exact


def test_truncated_data_phase_is_cancelled_and_requested_again(caplog):
    sim, camera, _ = make_rig(faults=PtpFaults(truncate_next=1))
    with caplog.at_level(logging.WARNING, logger="station.capture.ptp"):
        assert camera.capture().data == FRAME
    assert "data stopped after 149504 of 300012 bytes" in caplog.text
    assert ops(sim).count(OperationCode.GetObject) == 2


def test_data_phase_truncated_every_time_raises_incomplete_transfer():
    sim, camera, _ = make_rig(PtpConfig(**{**FAST.__dict__, "transfer_retries": 1}), faults=PtpFaults(truncate_next=5))
    with pytest.raises(IncompleteTransferError, match="stopped after 149504 of 300012 bytes, 2 times"):
        camera.capture()
    sim.faults.truncate_next = 0
    assert camera.capture().data == FRAME  # the cancel left the session usable


def test_disconnect_mid_transfer_raises_device_disconnected_naming_the_transfer():
    sim, camera, _ = make_rig(faults=PtpFaults(disconnect_after_bytes=100_000))
    with pytest.raises(DeviceDisconnectedError, match=r"GetObject .* after 100000 of 300012 bytes.*No such device") as caught:
        camera.capture()
    assert caught.value.exit_code == 3
    camera.close()
    assert usb.core.find(backend=SimUsbBackend(sim)) is None


def test_garbled_response_raises_protocol_error():
    sim, camera, _ = make_rig()
    sim.faults.corrupt_next_response = 1
    with pytest.raises(PtpProtocolError, match="unknown type"):
        camera.iso()


def test_full_card_raises_store_full():
    _, camera, _ = make_rig(max_objects=0)
    with pytest.raises(StoreFullError, match="StoreFull .* InitiateCapture"):
        camera.capture()


def test_session_left_open_by_a_crashed_process_is_reset_and_reopened():
    sim, first, _ = make_rig()
    first.transport.close()  # the process died: no CloseSession
    backend = SimUsbBackend(sim)
    with open_ptp_camera(backend=backend, config=FAST) as second:
        assert second.capture().data == FRAME
    assert ops(sim).count(OperationCode.OpenSession) == 3  # first, refused, after reset


def test_camera_claimed_by_another_program_is_a_device_error():
    sim, _camera, _ = make_rig()
    device = SimUsbDevice.for_camera(sim)
    backend = SimUsbBackend(device)
    usb.core.find(backend=backend).set_configuration()
    other = usb.core.find(backend=backend)
    usb.util.claim_interface(other, 0)
    with pytest.raises(DeviceError, match="Resource busy"):
        open_ptp_camera(backend=backend, config=FAST)


def test_device_without_a_ptp_interface_is_not_taken_for_a_camera():
    stick = SimUsbDevice(0x0781, 0x5581, interface_class=(8, 6, 80))
    with pytest.raises(CameraNotFoundError, match=r"no PTP camera .* saw 0781:5581 \(interfaces 8/6/80\)") as caught:
        open_ptp_camera(backend=SimUsbBackend(stick))
    assert caught.value.exit_code == 3


def test_vendor_filter_that_matches_nothing_names_the_wanted_id():
    with pytest.raises(CameraNotFoundError, match=r"matching 04a9:\*"):
        open_ptp_camera(backend=SimUsbBackend(SimPtpCamera(FrameRecorder())), vendor=0x04A9)


def test_empty_bus_says_no_usb_devices():
    with pytest.raises(CameraNotFoundError, match="no USB devices at all"):
        open_ptp_camera(backend=SimUsbBackend())


def test_default_backend_missing_raises_camera_not_found():
    if usb.backend.libusb1.get_backend() is not None:
        pytest.skip("libusb is installed: the answer depends on what is plugged in")
    with pytest.raises(CameraNotFoundError, match="no USB backend"):
        open_ptp_camera()


def test_the_station_camera_over_ptp_reports_itself_and_the_exposure_it_really_uses():
    from station.capture.still import CameraSettings, PtpStillCamera

    sim, camera, source = make_rig()
    still = PtpStillCamera(camera)
    try:
        used = still.apply(CameraSettings(1.0 / 30.0, 400))
        assert used == CameraSettings(0.0333, 400, 0.0)  # the body's 0.1 ms step, read back
        report = still.report()
        assert report.model == "station Sim PTP Camera" and report.raw_formats == ("dng",) and report.problems == []
        assert report.battery is None  # the simulated body does not list BatteryLevel
        with pytest.raises(DeviceError, match="no FNumber property"):
            still.apply(CameraSettings(0.01, 100, 8.0))
        assert still.trigger().download() == FRAME and source.shots[-1].iso == 400
    finally:
        still.close()


def test_a_ptp_body_without_raw_capture_is_a_problem_in_its_report():
    from station.capture.still import PtpStillCamera

    sim, camera, _ = make_rig()
    sim.info = replace(sim.info, capture_formats=(ObjectFormat.EXIF_JPEG,))
    camera.close()
    still = PtpStillCamera(open_ptp_camera(backend=SimUsbBackend(sim), config=FAST))
    try:
        assert still.report().problems == ["the camera offers no raw capture format (DNG or TIFF) over PTP"]
    finally:
        still.close()
