"""The GRBL emulator reproduces the firmware behaviour recorded in docs/rig.md, byte for byte."""

from __future__ import annotations

import math
import threading
import time

import pytest

from sim.grbl_firmware import FACTORY_SETTINGS, RIG_SETTINGS, GrblFirmware
from sim.grbl_motion import move_segment
from station.turntable.errors import GarbledStatusError
from station.turntable.status import parse_status

pytestmark = [pytest.mark.timeout(60), pytest.mark.no_kernels]
HALF_STEP = 0.5 / 44.444  # targets and stops land on whole motor steps


class ManualClock:
    """Deterministic time for the emulator: tests step it instead of sleeping."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def board(**kwargs: object) -> tuple[GrblFirmware, ManualClock]:
    clock = ManualClock()
    fw = GrblFirmware(clock=clock, settings=RIG_SETTINGS | kwargs.pop("settings", {}), **kwargs)
    fw.read()  # the power-on banner
    return fw, clock


def send(fw: GrblFirmware, data: bytes) -> str:
    fw.write(data)
    return fw.read().decode()


def test_power_on_prints_the_grbl_banner_and_grblhal_flavour_its_own():
    assert GrblFirmware().read() == b"\r\nGrbl 1.1h ['$' for help]\r\n"
    assert b"GrblHAL 1.1f ['$' or '$HELP' for help]" in GrblFirmware(flavour="grblhal").read()


def test_every_line_gets_one_ok_including_an_empty_line():
    fw, _ = board()
    assert send(fw, b"\n") == "ok\r\n"
    assert send(fw, b"G90\nG21\n") == "ok\r\nok\r\n"
    assert send(fw, b"$I\n") == "[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"


@pytest.mark.parametrize("line, reply", [
    (b"G7\n", "error:20"),  # unsupported G-code
    (b"G1X10\n", "error:22"),  # G1 with no feed ever set
    (b"X10F\n", "error:2"),  # bad number
    (b"G1X1X2F100\n", "error:25"),  # repeated word
    (b"G0G1X1\n", "error:21"),  # two motion words
    (b"$20=1\n", "error:10"),  # soft limits without homing
    (b"$Q\n", "error:3"),  # unknown $ command
    (b"G1X" + b"1" * 90 + b"F100\n", "error:11"),  # line overflow
])
def test_bad_lines_get_the_error_codes_real_firmware_sends(line, reply):
    fw, _ = board()
    assert send(fw, line) == f"{reply}\r\n"


def test_homing_while_moving_is_error_8_and_gcode_in_alarm_is_error_9():
    fw, clock = board(homing=True)
    assert fw.state == "Alarm"
    assert send(fw, b"G1X10F100\n") == "error:9\r\n"
    send(fw, b"$X\n")
    send(fw, b"G1X90F600\n")
    assert send(fw, b"$H\n") == "error:8\r\n"


def test_jog_beyond_travel_is_error_15_with_soft_limits():
    fw, _ = board(homing=True, soft_limits=True)
    send(fw, b"$X\n")
    assert send(fw, b"$J=G90Y5F100\n") == "error:15\r\n"  # machine travel is [-$131, 0], as in GRBL
    assert send(fw, b"$J=G90Y-500F100\n") == "error:15\r\n"
    assert send(fw, b"$J=G90Y-5F100\n") == "ok\r\n"


def test_motion_takes_the_trapezoid_time_scaled_and_g4_p0_answers_when_done():
    fw, clock = board(time_scale=0.5)
    assert send(fw, b"G1X90Y10F1800\n") == "ok\r\n"
    assert send(fw, b"G4P0\n") == ""  # no ok while the move runs
    seg = move_segment(0.0, (0.0, 0.0, 0.0), (90.0, 10.0, 0.0), (3600.0, 1800.0, 500.0), (180.0, 90.0, 10.0), 1800.0)
    clock.now += 0.5 * seg.duration - 1e-3
    assert fw.read() == b""
    assert fw.state == "Run"
    clock.now += 2e-3
    assert fw.read() == b"ok\r\n"
    assert fw.position() == pytest.approx((90.0, 10.0), abs=HALF_STEP)
    # feed 30 deg/s along the path; X's 180 deg/s^2 limits the path acceleration to 180 * |d| / dx
    length = math.hypot(90.0, 10.0)
    accel = 180.0 * length / 90.0
    assert seg.duration == pytest.approx(30.0 / accel + length / 30.0)


def test_position_is_readable_from_another_thread_during_motion():
    fw = GrblFirmware(time_scale=0.02, settings=RIG_SETTINGS)
    fw.write(b"G1X180F3600\n")
    seen: list[float] = []
    reader = threading.Thread(target=lambda: [seen.append(fw.position()[0]) or time.sleep(0.005) for _ in range(20)])
    reader.start()
    reader.join()
    assert seen == sorted(seen) and 0.0 < max(seen) <= 180.0 + HALF_STEP


def test_feed_hold_decelerates_then_holds_and_resume_is_ignored_until_hold_0():
    fw, clock = board()
    send(fw, b"G1X360F3600\n")
    clock.now += 1.0
    assert parse_status(send(fw, b"!?")).state == "Hold"
    assert parse_status(send(fw, b"?")).substate == 1
    send(fw, b"~")  # ignored during Hold:1
    clock.now += 0.2
    assert parse_status(send(fw, b"?")).substate == 1
    clock.now += 1.0
    held = parse_status(send(fw, b"?"))
    assert (held.state, held.substate) == ("Hold", 0)
    send(fw, b"~")
    assert parse_status(send(fw, b"?")).state == "Run"
    clock.now += 20.0
    assert fw.position()[0] == pytest.approx(360.0, abs=HALF_STEP)


def test_a_new_board_lists_grbl_factory_settings():
    fw = GrblFirmware()
    fw.read()
    listed = dict(line[1:].split("=") for line in send(fw, b"$$\n").split("\r\n") if line.startswith("$"))
    assert {int(k): float(v) for k, v in listed.items()} == FACTORY_SETTINGS
    assert (listed["100"], listed["110"], listed["120"], listed["130"]) == ("250.000", "500.000", "10.000", "200.000")


def test_system_commands_that_need_idle_are_error_8_while_moving_and_g_c_x_are_not():
    fw, clock = board()
    send(fw, b"G1X90F600\n")
    for command in (b"$I\n", b"$#\n", b"$N\n", b"$$\n", b"$N0=G21\n", b"$100=44.444\n", b"$C\n"):
        assert send(fw, command) == "error:8\r\n", command
    assert send(fw, b"$G\n").endswith("ok\r\n")
    assert send(fw, b"$X\n") == "ok\r\n"  # no alarm to clear: no effect, as on real GRBL
    clock.now += 20.0
    assert send(fw, b"$#\n").startswith("[G54:0.000,0.000,0.000]")


def test_reset_mid_move_answers_the_pending_dwell_before_alarm_3():
    fw, clock = board()
    send(fw, b"G1X90F600\n")
    assert send(fw, b"G4P0\n") == ""
    clock.now += 1.0
    assert send(fw, b"\x18").startswith("ok\r\nALARM:3\r\n\r\nGrbl 1.1h")


def test_startup_lines_are_stored_run_after_each_reset_and_echoed():
    fw, clock = board()
    assert send(fw, b"$N\n") == "$N0=\r\n$N1=\r\nok\r\n"
    assert send(fw, b"$N0=G20\n") == "ok\r\n"
    assert send(fw, b"$N\n") == "$N0=G20\r\n$N1=\r\nok\r\n"
    assert send(fw, b"\x18") == "\r\nGrbl 1.1h ['$' for help]\r\n>G20:ok\r\n"
    assert "G20" in send(fw, b"$G\n")
    send(fw, b"G1X1F10\n")  # inches: one inch is 25.4 degrees of turntable
    clock.now += 300.0
    assert fw.position()[0] == pytest.approx(25.4, abs=HALF_STEP)
    fw.power_cycle()
    assert fw.read().endswith(b">G20:ok\r\n")  # EEPROM: kept through a power cycle


def test_check_mode_parses_without_moving_and_leaving_it_resets():
    fw, clock = board()
    assert send(fw, b"$C\n") == "[MSG:Enabled]\r\nok\r\n"
    assert send(fw, b"G1X90F600\n") == "ok\r\n"
    assert parse_status(send(fw, b"?")).state == "Check"
    clock.now += 20.0
    assert fw.position() == (0.0, 0.0)
    assert send(fw, b"$C\n") == "[MSG:Disabled]\r\nok\r\n\r\nGrbl 1.1h ['$' for help]\r\n"


def test_g54_from_g10_l20_survives_reset_and_power_cycle_while_g92_does_not():
    fw, clock = board()
    send(fw, b"G1X30F3600\n")
    clock.now += 10.0
    assert send(fw, b"G10L20P1X100Y5\n") == "ok\r\n"
    assert send(fw, b"$#\n").startswith("[G54:-70.000,-5.000,0.000]")
    send(fw, b"G92X0\n")
    assert parse_status(send(fw, b"?")).wco == (30.0, -5.0, 0.0)
    send(fw, b"\x18")
    assert parse_status(send(fw, b"?")).wco == (-70.0, -5.0, 0.0)  # G92 gone, G54 kept
    fw.power_cycle()
    fw.read()
    assert parse_status(send(fw, b"?")).wco == (-70.0, -5.0, 0.0)


def test_feed_override_slows_the_next_move_and_shows_in_the_status_report():
    fw, clock = board()
    for _ in range(6):
        fw.write(b"\x92")  # -10 % each
    reports = [parse_status(send(fw, b"?")) for _ in range(2)]  # Ov comes on the next report without WCO
    assert [r.overrides for r in reports if r.overrides] == [(40, 100, 100)]
    send(fw, b"G1X90F1800\n")
    full = move_segment(0.0, (0.0,) * 3, (90.0, 0.0, 0.0), (3600.0, 1800.0, 500.0), (180.0, 90.0, 10.0), 1800.0)
    clock.now += full.duration + 0.1
    assert parse_status(send(fw, b"?")).state == "Run"  # 40 % of the feed: far from done
    assert parse_status(send(fw, b"?")).feed == pytest.approx(720.0, abs=1.0)
    send(fw, b"!")
    clock.now += 5.0
    send(fw, b"\x18")  # from Hold:0: back to 100 % like every reset
    assert [parse_status(send(fw, b"?")).overrides for _ in range(2)][1] == (100, 100, 100)


def test_reset_during_motion_gives_alarm_3_banner_and_unlock_message():
    fw, clock = board()
    send(fw, b"G1X90F600\n")
    clock.now += 1.0
    assert send(fw, b"\x18") == "ALARM:3\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n"
    assert send(fw, b"G1X0F600\n") == "error:9\r\n"
    assert send(fw, b"$X\n") == "[MSG:Caution: Unlocked]\r\nok\r\n"
    assert 0.0 < fw.position()[0] < 90.0  # it stopped where it was


def test_soft_limit_alarm_2_ignores_everything_until_reset():
    fw, clock = board(homing=True, soft_limits=True)
    send(fw, b"$X\n")
    assert send(fw, b"G1Y-500F100\n") == "ALARM:2\r\n[MSG:Reset to continue]\r\n"
    assert send(fw, b"$X\n?") == ""
    assert send(fw, b"\x18") == "ok\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n"


def test_homing_enabled_boots_into_alarm_and_homing_answers_ok_when_done():
    clock = ManualClock()
    fw = GrblFirmware(homing=True, clock=clock)
    assert fw.read().endswith(b"[MSG:'$H'|'$X' to unlock]\r\n")
    assert send(fw, b"$H\n") == ""
    assert fw.state == "Home"
    clock.now += 5.0
    assert fw.read() == b"ok\r\n"
    assert fw.state == "Idle"


def test_status_reports_parse_by_key_and_grblhal_puts_bf_before_fs():
    fw, _ = board(flavour="grblhal")
    line = send(fw, b"?").strip()
    assert line.index("|Bf:") < line.index("|FS:")
    report = parse_status(line)
    assert report.state == "Idle" and report.buffer == (35, 1023) and report.mpos == (0.0, 0.0, 0.0)


def test_garble_fault_makes_exactly_the_next_n_reports_unparseable():
    fw, _ = board()
    fw.faults.garble_status = 5
    for _ in range(5):
        with pytest.raises(GarbledStatusError):
            parse_status(send(fw, b"?").strip())
    assert parse_status(send(fw, b"?").strip()).state == "Idle"


def test_dropped_ok_fault_swallows_exactly_one_reply():
    fw, _ = board()
    fw.faults.drop_ok = 1
    assert send(fw, b"G90\n") == ""
    assert send(fw, b"G90\n") == "ok\r\n"


def test_power_cycle_zeroes_the_counter_but_not_the_physical_stage():
    fw, clock = board()
    send(fw, b"G1X45F600\n")
    clock.now += 10.0
    fw.power_cycle()
    assert fw.read() == b"\r\nGrbl 1.1h ['$' for help]\r\n"
    assert parse_status(send(fw, b"?")).mpos == (0.0, 0.0, 0.0)
    assert fw.position() == pytest.approx((45.0, 0.0), abs=HALF_STEP)


def test_a_starved_cycle_stops_idle_part_way_and_only_a_cycle_start_finishes_the_move():
    """As grbl-sim did on a loaded host: the stepper ran dry, GRBL ended the cycle with the block still
    planned, and G4 P0 (protocol_buffer_synchronize) waits for a `~` that GRBL itself never sends."""
    fw, clock = board()
    fw.faults.starve_on_move = 1
    assert send(fw, b"G1X90F600\nG4P0\n") == "ok\r\n"
    clock.now += 20.0  # twice the move's 9.06 s
    stalled = parse_status(send(fw, b"?").strip())
    assert stalled.state == "Idle" and stalled.mpos[0] == pytest.approx(45.0, abs=HALF_STEP)
    assert send(fw, b"~") == ""
    clock.now += 2.0
    assert parse_status(send(fw, b"?").strip()).state == "Run"
    clock.now += 3.0  # the other 45 deg take 4.5 s
    assert fw.read() == b"ok\r\n"  # the dwell's
    done = parse_status(send(fw, b"?").strip())
    assert done.state == "Idle" and done.mpos[0] == pytest.approx(90.0, abs=HALF_STEP)


def test_a_cycle_start_during_a_dwell_neither_moves_nor_lengthens_it():
    """Idle with no move planned, as while G4 waits: `~` must not start (or restart) anything."""
    fw, clock = board()
    assert send(fw, b"G4P1\n") == ""
    clock.now += 0.6
    assert send(fw, b"~") == ""
    clock.now += 0.5  # 1.1 s after the dwell began
    assert fw.read() == b"ok\r\n"
    assert parse_status(send(fw, b"?").strip()).mpos[0] == 0.0


def test_vanish_fault_unplugs_halfway_through_the_move_and_replugs_later():
    fw, clock = board()
    fw.faults.vanish_on_move = 1
    fw.faults.replug_after_s = 1.0
    send(fw, b"G1X90F600\n")
    clock.now += 5.0  # the move lasts 9.06 s: 10 deg/s after 0.06 s of acceleration
    assert fw.read() == b""
    assert not fw.plugged and fw.generation == 1
    assert math.isclose(fw.position()[0], 45.0, abs_tol=HALF_STEP)
    clock.now += 100.0
    fw.read()
    assert fw.plugged and fw.state == "Idle"


def test_jog_cancel_stops_a_jog_short_and_returns_to_idle():
    fw, clock = board()
    assert send(fw, b"$J=G91X90F600\n") == "ok\r\n"
    clock.now += 2.0
    assert parse_status(send(fw, b"?")).state == "Jog"
    send(fw, b"\x85")
    clock.now += 1.0
    assert parse_status(send(fw, b"?")).state == "Idle"
    assert 15.0 < fw.position()[0] < 30.0


def test_safety_door_holds_like_feed_hold_and_cycle_start_resumes():
    fw, clock = board()
    send(fw, b"G1X90F600\n")
    clock.now += 1.0
    send(fw, b"\x84")
    clock.now += 1.0
    door = parse_status(send(fw, b"?"))
    assert (door.state, door.substate) == ("Door", 0)
    send(fw, b"~")
    clock.now += 20.0
    assert fw.position()[0] == pytest.approx(90.0, abs=HALF_STEP)
