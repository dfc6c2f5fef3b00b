"""The GRBL turntable driver, driven through pyserial's real code path against the emulator.

Each injected hazard from docs/rig.md ends either recovered (and verified against where the
emulated stage physically is) or in a typed error naming the fault.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.grbl_links import FakeTurntable, NmeaDevice, SilentDevice, attach, register_url_scheme, start_fake_turntable
from station.errors import BadInputError, DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from station.turntable.errors import (
    GarbledStatusError,
    GrblAlarm,
    GrblError,
    GrblSettingsError,
    MoveCancelledError,
    NotGrblError,
    ReferenceMismatchError,
    SoftLimitError,
    TiltLimitError,
    UnexpectedResetError,
    WaitTimeoutError,
)
from station.turntable.grbl import Turntable, TurntableConfig
from station.turntable.planning import move_seconds, trapezoid_seconds
from station.turntable.reference import Reference
from station.turntable.status import parse_status

pytestmark = [pytest.mark.timeout(60), pytest.mark.no_kernels]
FAST = TurntableConfig(banner_timeout_s=1.0, reply_timeout_s=0.5, motion_margin_s=1.0, reconnect_timeout_s=3.0)
SCALE = 0.02  # emulated motion runs 50x faster than the real table
HALF_STEP = 0.5 / 44.444 + 1e-3  # GRBL lands on whole steps; reports carry 3 decimals


@pytest.fixture(params=["url", "pty"])
def route(request: pytest.FixtureRequest) -> str:
    return request.param


@contextmanager
def rig(route: str = "url", **firmware: object) -> Iterator[tuple[FakeTurntable, Turntable]]:
    with start_fake_turntable(route, time_scale=SCALE, **firmware) as fake:
        table = Turntable.connect(fake.port, FAST)
        try:
            yield fake, table
        finally:
            table.close()


def angle_error(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_moves_reach_the_target_on_the_stage_itself(route):
    with rig(route) as (fake, table):
        assert table.info.flavour == "Grbl" and table.info.build.startswith("1.1h")
        for angle, tilt in [(90.0, 30.0), (200.0, 45.0), (10.0, 0.0)]:
            reached = table.move_to(angle, tilt).wait(5.0)
            assert angle_error(reached[0], angle) < 0.03 and abs(reached[1] - tilt) < 0.03
            stage = fake.firmware.position()
            assert angle_error(stage[0], angle) < HALF_STEP and stage[1] == pytest.approx(tilt, abs=HALF_STEP)


def test_shortest_rotation_goes_backwards_and_continuous_always_forwards():
    with rig() as (_, table):
        table.move_to(350.0, 0.0).wait(5.0)
        assert table.position()[0] == pytest.approx(-10.0, abs=HALF_STEP)  # -10 is shorter than +350
        assert table.move_to(10.0, 0.0, rotation="continuous").wait(5.0)[0] == pytest.approx(10.0, abs=HALF_STEP)
        assert table.move_to(5.0, 0.0, rotation="continuous").wait(5.0)[0] == pytest.approx(5.0 + 360.0 - 360.0, abs=HALF_STEP)


def test_x_stays_inside_its_window_however_many_turns_a_scan_makes():
    with start_fake_turntable(time_scale=0.005) as fake:
        with Turntable.connect(fake.port, replace(FAST, x_range_deg=(-180.0, 540.0))) as table:
            seen = []
            for _ring in range(3):
                for angle in (0.0, 120.0, 240.0):
                    seen.append(table.move_to(angle, 0.0, rotation="continuous").wait(10.0)[0])
            assert max(seen) <= 540.0 and min(seen) >= -180.0
            assert seen[:6] == pytest.approx([0.0, 120.0, 240.0, 360.0, 480.0, 240.0], abs=HALF_STEP)  # one unwind
            assert angle_error(fake.firmware.position()[0], 240.0) < HALF_STEP


def test_soft_limits_are_checked_before_anything_is_sent():
    with rig(homing=True, soft_limits=True, settings={130: 300.0}) as (_, table):
        with pytest.raises(SoftLimitError, match="narrower than one turn"):
            table.move_to(90.0, 0.0)
    with rig(homing=True, soft_limits=True, settings={130: 720.0}) as (fake, table):
        assert table.settings()[20] == 1
        with pytest.raises(SoftLimitError, match=r"\$131=200"):
            table.move_to(0.0, 30.0)  # tilt travel is [-200, 0] machine, and work = machine here
        assert table.move_to(-90.0, 0.0).wait(5.0)[0] == pytest.approx(-90.0, abs=HALF_STEP)
        assert table.move_to(90.0, 0.0).wait(5.0)[0] == pytest.approx(-270.0, abs=HALF_STEP)  # wrapped into travel
        assert fake.firmware.state == "Idle"


def test_grblhal_board_is_identified_and_driven():
    with rig(flavour="grblhal") as (fake, table):
        assert table.info.flavour == "GrblHAL"
        table.move_to(45.0, 10.0).wait(5.0)
        assert fake.firmware.position() == pytest.approx((45.0, 10.0), abs=HALF_STEP)


@pytest.mark.parametrize("port", ["/dev/ttyNOSUCHTURNTABLE", "fakegrbl://nobody-home"])
def test_a_port_that_does_not_exist_is_a_device_error_naming_it(port):
    register_url_scheme()
    with pytest.raises(DeviceError, match=port):
        Turntable.connect(port, FAST)


def test_a_device_answering_garbage_is_not_grbl(route):
    with attach(NmeaDevice(), route) as fake:
        with pytest.raises(NotGrblError, match="does not answer like GRBL") as caught:
            Turntable.connect(fake.port, FAST)
        assert caught.value.port == fake.port and "$GPGGA" in caught.value.heard
        assert caught.value.exit_code == 3


def test_a_silent_port_times_out_as_a_device_timeout():
    with attach(SilentDevice()) as fake:
        with pytest.raises(DeviceTimeoutError, match="no answer from"):
            Turntable.connect(fake.port, FAST)


def test_settings_that_differ_from_the_rig_are_refused_with_each_mismatch_named():
    with start_fake_turntable(settings={100: 40.0, 121: 50.0}) as fake:
        with pytest.raises(GrblSettingsError, match=r"\$100=40 \(expected 44.444.*\$121=50"):
            Turntable.connect(fake.port, FAST)


def test_tilt_outside_limits_is_bad_input_and_nothing_moves():
    with rig() as (fake, table):
        with pytest.raises(TiltLimitError, match="outside the limits") as caught:
            table.move_to(0.0, 95.0)
        assert isinstance(caught.value, BadInputError) and caught.value.exit_code == 2
        assert fake.firmware.state == "Idle" and fake.firmware.position() == (0.0, 0.0)


def test_firmware_errors_become_typed_exceptions_with_their_meaning():
    with rig() as (_, table):
        with pytest.raises(GrblError, match="error:5") as caught:
            table.home().wait(5.0)  # homing is disabled on this board
        assert caught.value.code == 5 and "homing" in caught.value.meaning.lower()


def test_homing_board_is_homed_at_connect():
    with rig(homing=True) as (fake, table):
        assert table.homing_enabled and fake.firmware.state == "Idle"
        assert table.position() == pytest.approx((0.0, 0.0))


def test_dropped_ok_on_the_move_and_on_the_barrier_still_completes(route):
    with rig(route) as (fake, table):
        fake.firmware.faults.drop_ok = 1
        assert table.move_to(120.0, 20.0).wait(5.0) == pytest.approx((120.0, 20.0), abs=HALF_STEP)
        fake.firmware.faults.drop_ok = 2
        assert table.move_to(60.0, 10.0).wait(5.0) == pytest.approx((60.0, 10.0), abs=HALF_STEP)
        assert fake.firmware.position() == pytest.approx((60.0, 10.0), abs=HALF_STEP)


def test_one_garbled_status_is_retried_two_are_a_typed_error():
    with rig() as (fake, table):
        fake.firmware.faults.garble_status = 1
        assert table.status().state == "Idle"
        fake.firmware.faults.garble_status = 2
        with pytest.raises(GarbledStatusError, match="garbled"):
            table.status()


def test_feed_hold_then_resume_finishes_the_move():
    with start_fake_turntable(time_scale=0.3) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            moving = table.move_to(180.0, 0.0, rotation="continuous")  # about 1 s of emulated motion
            time.sleep(0.3)
            table.feed_hold()
            table.resume(timeout=5.0)
            assert moving.wait(10.0)[0] == pytest.approx(180.0, abs=HALF_STEP)
            assert fake.firmware.position()[0] == pytest.approx(180.0, abs=HALF_STEP)


def test_operator_cancel_stops_without_alarm_and_keeps_the_position():
    with start_fake_turntable(time_scale=0.3) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            moving = table.move_to(180.0, 0.0, rotation="continuous")
            time.sleep(0.3)
            table.cancel(timeout=5.0)
            with pytest.raises(MoveCancelledError, match="cancelled by the operator"):
                moving.wait(10.0)
            assert not isinstance(moving.exception, DeviceError)
            assert fake.firmware.state == "Idle"
            stopped = fake.firmware.position()
            assert 0.0 < stopped[0] < 180.0
            assert table.position() == pytest.approx(stopped, abs=HALF_STEP)
            table.move_to(270.0, 5.0).wait(10.0)
            stage = fake.firmware.position()
            assert angle_error(stage[0], 270.0) < HALF_STEP and stage[1] == pytest.approx(5.0, abs=HALF_STEP)


def test_giving_up_waiting_is_not_a_device_timeout():
    with start_fake_turntable(time_scale=0.3) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            moving = table.move_to(180.0, 0.0, rotation="continuous")
            with pytest.raises(WaitTimeoutError) as caught:
                moving.wait(0.01)
            assert not isinstance(caught.value, DeviceTimeoutError)
            assert moving.wait(10.0)[0] == pytest.approx(180.0, abs=HALF_STEP)


def test_alarm_mid_scan_is_typed_and_recovery_keeps_the_counted_position_flagged_inexact():
    with rig() as (fake, table):
        fake.firmware.faults.alarm_on_move = 2
        table.move_to(90.0, 0.0).wait(5.0)
        with pytest.raises(GrblAlarm, match="ALARM:1") as caught:
            table.move_to(180.0, 30.0).wait(5.0)
        assert caught.value.code == 1 and "Hard limit" in caught.value.meaning
        recovery = table.recover()
        assert not recovery.exact and not recovery.rehomed  # GRBL: a sudden halt likely lost steps
        stage = fake.firmware.position()
        assert recovery.position == pytest.approx(stage, abs=HALF_STEP)  # restored where it stopped
        table.move_to(180.0, 30.0).wait(5.0)
        assert fake.firmware.position() == pytest.approx((180.0, 30.0), abs=HALF_STEP)


def test_board_reset_mid_move_with_homing_rehomes_and_the_next_move_is_exact(route):
    with rig(route, homing=True) as (fake, table):
        table.move_to(300.0, 20.0, rotation="continuous").wait(5.0)
        fake.firmware.faults.reset_on_move = 1
        with pytest.raises(UnexpectedResetError, match="reset itself"):
            table.move_to(100.0, 40.0, rotation="continuous").wait(5.0)
        recovery = table.recover()
        assert recovery.rehomed and recovery.exact
        table.move_to(100.0, 40.0, rotation="continuous").wait(5.0)
        stage = fake.firmware.position()
        assert angle_error(stage[0], 100.0) < HALF_STEP and stage[1] == pytest.approx(40.0, abs=HALF_STEP)


def test_a_move_whose_cycle_ended_part_way_is_restarted_and_ends_at_its_target(route, caplog):
    with rig(route) as (fake, table):
        fake.firmware.faults.starve_on_move = 1
        assert table.move_to(90.0, 40.0).wait(5.0) == pytest.approx((90.0, 40.0), abs=HALF_STEP)
        assert fake.firmware.position() == pytest.approx((90.0, 40.0), abs=HALF_STEP)
    assert "short of (90.0, 40.0) with its move unfinished; sending cycle start" in caplog.text


def test_board_reset_mid_move_without_homing_is_restored_but_flagged_inexact():
    with rig() as (fake, table):
        fake.firmware.faults.reset_on_move = 1
        with pytest.raises(UnexpectedResetError):
            table.move_to(90.0, 40.0).wait(5.0)
        recovery = table.recover()
        assert not recovery.rehomed and not recovery.exact
        assert recovery.position == pytest.approx((0.0, 0.0), abs=HALF_STEP)  # the last position it saw
        assert fake.firmware.position()[0] > 1.0  # ...while the stage stopped part-way: hence inexact


def test_board_reset_while_idle_without_homing_restores_the_exact_position():
    with rig() as (fake, table):
        table.move_to(75.0, 15.0).wait(5.0)
        fake.firmware.power_cycle()
        with pytest.raises(UnexpectedResetError):
            table.move_to(150.0, 15.0).wait(5.0)
        recovery = table.recover()
        assert recovery.exact and recovery.position == pytest.approx((75.0, 15.0), abs=HALF_STEP)
        table.move_to(150.0, 15.0).wait(5.0)
        assert fake.firmware.position() == pytest.approx((150.0, 15.0), abs=HALF_STEP)


def test_port_vanishing_mid_move_reconnects_after_replug_and_rehomes(route):
    with rig(route, homing=True) as (fake, table):
        fake.firmware.faults.vanish_on_move = 1
        fake.firmware.faults.replug_after_s = 0.3
        with pytest.raises(DeviceDisconnectedError, match="vanished"):
            table.move_to(200.0, 30.0).wait(5.0)
        recovery = table.recover()
        assert recovery.rehomed
        table.move_to(200.0, 30.0).wait(5.0)
        stage = fake.firmware.position()
        assert angle_error(stage[0], 200.0) < HALF_STEP and stage[1] == pytest.approx(30.0, abs=HALF_STEP)


def test_port_that_never_comes_back_fails_recovery_with_a_disconnect():
    with rig() as (fake, table):
        fake.firmware.faults.vanish_on_move = 1
        fake.firmware.faults.replug_after_s = None
        with pytest.raises(DeviceDisconnectedError):
            table.move_to(200.0, 30.0).wait(5.0)
        with pytest.raises(DeviceDisconnectedError, match="did not come back"):
            table.recover()


def test_connect_repeats_the_reset_when_a_booting_board_ignored_the_first():
    with start_fake_turntable() as fake:
        fake.firmware.faults.ignore_resets = 1
        with pytest.raises(DeviceTimeoutError, match="no answer"):
            Turntable.connect(fake.port, replace(FAST, banner_retry_s=5.0))  # one reset only
        fake.firmware.faults.ignore_resets = 1
        with Turntable.connect(fake.port, replace(FAST, banner_retry_s=0.3)) as table:
            assert table.info.version == "1.1h"


def test_connect_holds_a_moving_table_before_its_reset_so_no_alarm_3():
    with start_fake_turntable(time_scale=0.3) as fake:
        fake.firmware.write(b"G1X300F1800\n")  # a previous driver was killed mid-move
        time.sleep(0.1)
        with Turntable.connect(fake.port, FAST) as table:
            assert table.position_exact and fake.firmware.state == "Idle"
            stopped = fake.firmware.position()
            assert 0.0 < stopped[0] < 300.0
            assert table.position() == pytest.approx(stopped, abs=HALF_STEP)


def test_a_reset_that_catches_the_table_moving_is_never_called_exact(caplog):
    with start_fake_turntable(time_scale=0.3) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            moving = table.move_to(170.0, 0.0)
            time.sleep(0.2)
            fake.firmware.write(b"\x18")  # someone else resets it mid-move: ok to G4 P0, then ALARM:3
            with pytest.raises(GrblAlarm, match="ALARM:3"):
                moving.wait(5.0)
            recovery = table.recover()
            assert not recovery.exact and not table.position_exact
            assert "not exact" in caplog.text


def test_a_stored_g20_startup_line_is_overridden_so_degrees_stay_degrees():
    with start_fake_turntable(time_scale=SCALE) as fake:
        fake.firmware.startup_lines[0] = "G20"
        with Turntable.connect(fake.port, FAST) as table:
            assert table.info.startup_lines == ("G20",)
            table.move_to(10.0, 5.0).wait(5.0)
            assert fake.firmware.position() == pytest.approx((10.0, 5.0), abs=HALF_STEP)


def test_the_reference_restored_after_a_reboot_survives_the_next_connect():
    with start_fake_turntable(time_scale=SCALE) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            table.move_to(100.0, 20.0).wait(5.0)
            fake.firmware.power_cycle()  # MPos restarts at zero where the table stands
            with pytest.raises(UnexpectedResetError):
                table.move_to(150.0, 20.0).wait(5.0)
            assert table.recover().exact
            assert table.reference.g54[0] == pytest.approx(-100.0, abs=HALF_STEP)
            table.move_to(150.0, 20.0).wait(5.0)
        with Turntable.connect(fake.port, FAST) as table:  # a restarted `station` soft-resets the board
            assert table.position_exact
            assert table.position() == pytest.approx((150.0, 20.0), abs=HALF_STEP)
            table.move_to(200.0, 30.0).wait(5.0)
            assert fake.firmware.position() == pytest.approx((200.0, 30.0), abs=HALF_STEP)


def test_a_board_powered_up_since_its_reference_was_set_is_not_called_exact(caplog):
    with start_fake_turntable(time_scale=SCALE) as fake:
        with Turntable.connect(fake.port, FAST) as table:
            table.move_to(100.0, 20.0).wait(5.0)
            table.reference_to((10.0, 5.0), exact=True)  # G54 now (90, 15)
        fake.firmware.power_cycle()  # while no `station` runs: MPos restarts at zero
        with Turntable.connect(fake.port, FAST) as table:
            assert not table.position_exact
        assert "as after a power-up" in caplog.text


def test_a_wco_that_disagrees_with_the_stored_g54_is_refused():
    with start_fake_turntable() as fake:
        fake.firmware.startup_lines[0] = "G92X5"  # G92.1 clears it; a board that kept it would be refused
        with Turntable.connect(fake.port, FAST) as table:
            assert table.reference.g92 == (0.0, 0.0, 0.0)
    with pytest.raises(ReferenceMismatchError, match="WCO"):
        Reference((1.0, 0.0, 0.0), (0.0, 0.0, 0.0)).check(parse_status("<Idle|MPos:0,0,0|WCO:0,0,0>"), "port")


def test_a_40_percent_feed_override_does_not_time_out_a_move():
    with start_fake_turntable() as fake:  # real time: the allowance is all that stands between
        with Turntable.connect(fake.port, replace(FAST, motion_margin_s=0.05)) as table:
            for _ in range(6):
                fake.firmware.write(b"\x92")  # the operator turns the feed knob down to 40 %
            assert [table.status().overrides for _ in range(2)][1] == (40, 100, 100)
            assert table.move_to(30.0, 0.0).wait(30.0) == pytest.approx((30.0, 0.0), abs=HALF_STEP)


def test_move_time_follows_the_vector_feed_and_the_feed_override():
    rates, accels = (3600.0, 1800.0), (180.0, 90.0)
    alone = move_seconds((90.0, 0.0), 1800.0, rates, accels)
    assert alone == pytest.approx(trapezoid_seconds(90.0, 1800.0, 180.0))
    combined = move_seconds((90.0, 90.0), 1800.0, rates, accels)  # F is the speed along the diagonal
    length = math.hypot(90.0, 90.0)
    assert combined == pytest.approx(trapezoid_seconds(length, 1800.0, 90.0 * math.sqrt(2.0)))
    assert move_seconds((90.0, 0.0), 1800.0, rates, accels, 40.0) > 2.4 * alone - 1.0
    assert move_seconds((90.0, 0.0), 7200.0, rates, accels) == pytest.approx(trapezoid_seconds(90.0, 3600.0, 180.0))


def test_poll_rate_above_5_hz_is_refused():
    with pytest.raises(BadInputError, match="poll_hz"):
        TurntableConfig(poll_hz=10.0)


# ---- status parser ---------------------------------------------------------------------------
_coords = st.tuples(*[st.floats(-1e4, 1e4, allow_nan=False).map(lambda v: round(v, 3))] * 3)


@settings(max_examples=60, deadline=None)
@given(mpos=_coords, wco=_coords, feed=st.integers(0, 5000), data=st.data())
def test_status_reports_parse_by_key_in_any_order_with_any_fields_missing(mpos, wco, feed, data):
    fields = {
        "MPos": ",".join(f"{v:.3f}" for v in mpos),
        "FS": f"{feed},0",
        "WCO": ",".join(f"{v:.3f}" for v in wco),
        "Bf": "15,128",
        "Pn": "XY",
        "Ov": "100,100,100",
        "A": "SF",
    }
    keep = ["MPos"] + data.draw(st.lists(st.sampled_from(list(fields)[1:]), unique=True))
    order = data.draw(st.permutations(keep))
    report = parse_status("<Hold:1|" + "|".join(f"{k}:{fields[k]}" for k in order) + ">")
    assert (report.state, report.substate, report.mpos) == ("Hold", 1, mpos)
    assert report.wco == (wco if "WCO" in keep else None)
    assert report.feed == (feed if "FS" in keep else None)
    assert report.buffer == ((15, 128) if "Bf" in keep else None)
    assert report.pins == ("XY" if "Pn" in keep else "")


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(1, 40))
def test_a_truncated_status_report_is_always_refused(cut):
    line = "<Run|MPos:12.500,3.000,0.000|FS:1800,0|WCO:0.000,0.000,0.000>"
    with pytest.raises(GarbledStatusError):
        parse_status(line[: min(cut, len(line) - 1)])


@pytest.mark.parametrize("line", [
    "<Idle|MPos:1.0,2.0|FS:0,0>extra>",
    "<Idel|MPos:0,0,0>",
    "<Idle|MPos:0.0,2.p,0.0>",
    "<Idle|FS:0,0>",
    "<Idle|MPos:0,0,0|WCO:0,0>",
    "<Idle|MPos:0,0,0|MPos:1,1,1>",
])
def test_corrupted_status_reports_are_refused(line):
    with pytest.raises(GarbledStatusError):
        parse_status(line)


def test_work_position_comes_from_wpos_or_mpos_minus_the_last_wco():
    report = parse_status("<Idle|MPos:10.000,5.000,0.000|FS:0,0|TLR>")
    assert report.work_position((1.0, 1.0, 0.0)) == (9.0, 4.0, 0.0)
    assert report.extra == {"TLR": ""}
    assert parse_status("<Idle|WPos:1.000,2.000,3.000>").work_position(None) == (1.0, 2.0, 3.0)
