"""`station rig check`: the operator's first command on a new rig, against the emulated board, the simulated
camera, and (when gcc and ../shared are there) the real GRBL 1.1h firmware built as grbl-sim."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from grbl_sim_support import SHARED_GRBL_SIM, GrblSimBridge, build_grbl_sim
from sim.grbl_links import start_fake_turntable
from station.cli import app
from station.cli_rig import compare_settings
from station.config import parse_config

runner = CliRunner()


def write_config(tmp_path: Path, port: str, extra: str = "") -> Path:
    path = tmp_path / "station.toml"
    path.write_text(f"""
[rig]
width = 64
height = 48
focal_px = 112.0
[turntable]
port = "{port}"
[camera]
backend = "sim"
{extra}
""")
    return path


def check(config: Path) -> tuple[int, dict]:
    result = runner.invoke(app, ["rig", "check", "--config", str(config), "--json"])
    report = json.loads(result.stdout[result.stdout.index("{"):result.stdout.rindex("}") + 1])
    return result.exit_code, {(f["part"], f["item"]): f for f in report["findings"]}


def test_a_rig_that_matches_its_config_passes_with_firmware_settings_move_and_test_shot(tmp_path):
    code, found = check(write_config(tmp_path, "fakegrbl://"))
    assert code == 0, found
    assert "Grbl 1.1h" in found["turntable", "firmware"]["detail"]
    assert {f"${n}" for n in (20, 22, 100, 101, 110, 111, 120, 121, 130, 131)} <= {item for _, item in found}
    assert "turned 5 deg and back" in found["turntable", "test move"]["detail"]
    assert found["camera", "model"]["detail"].startswith("station Sim PTP Camera")
    assert found["camera", "test shot"]["detail"] == "64x48 dng, CFA RGGB"
    assert all(f["ok"] for f in found.values())


def test_a_board_set_up_differently_fails_naming_each_setting_and_both_values(tmp_path):
    with start_fake_turntable(time_scale=0.05, settings={100: 50.0, 121: 45.0}) as board:
        code, found = check(write_config(tmp_path, board.port))
    assert code == 3
    assert not found["turntable", "$100"]["ok"] and found["turntable", "$100"]["detail"] == "50 (config expects 44.444)"
    assert not found["turntable", "$121"]["ok"] and "45 (config expects 90)" in found["turntable", "$121"]["detail"]
    assert found["turntable", "$110"]["ok"] and found["turntable", "firmware"]["ok"]


def test_homing_expected_but_off_on_the_board_is_a_failed_check_with_the_reason_on_stderr(tmp_path):
    result = runner.invoke(app, ["rig", "check", "--config", str(write_config(tmp_path, "fakegrbl://", "[turntable.x]"))])
    assert result.exit_code == 2 and "turntable.x: unknown key" in " ".join(result.output.split())
    config = write_config(tmp_path, "fakegrbl://").read_text().replace('[camera]', 'homing = true\n[camera]')
    (tmp_path / "station.toml").write_text(config)
    result = runner.invoke(app, ["rig", "check", "--config", str(tmp_path / "station.toml")])
    said = " ".join(result.output.split())
    assert result.exit_code == 3
    assert "FAIL turntable $22" in said and "turntable $22: 0 (config expects 1)" in said


def test_a_camera_delivering_another_raw_format_than_configured_fails_the_test_shot(tmp_path):
    code, found = check(write_config(tmp_path, "fakegrbl://", 'raw_format = "nef"'))
    assert code == 3
    assert not found["camera", "test shot"]["ok"] and "raw_format" in found["camera", "test shot"]["detail"]


def test_no_turntable_at_the_port_fails_the_connect_and_names_the_port(tmp_path):
    code, found = check(write_config(tmp_path, str(tmp_path / "ttyNOPE")))
    assert code == 3
    assert not found["turntable", "connect"]["ok"] and "ttyNOPE" in found["turntable", "connect"]["detail"]
    assert not found["camera", "connect"]["ok"]  # the simulated camera renders at the table's pose


def test_travel_must_reach_the_config_only_where_soft_limits_enforce_it():
    table = parse_config({"turntable": {"max_travel_deg": [720.0, 90.0]}}, "t.toml").turntable
    settings = {20: 0.0, 22: 0.0, 100: 44.444, 101: 44.444, 110: 3600.0, 111: 1800.0, 120: 180.0, 121: 90.0,
                130: 200.0, 131: 200.0}
    found = {f.item: f for f in compare_settings(settings, table)}
    assert found["$130"].ok and "does not enforce" in found["$130"].detail
    table = parse_config({"turntable": {"soft_limits": True, "homing": True}}, "t.toml").turntable
    found = {f.item: f for f in compare_settings(settings | {20: 1.0, 22: 1.0}, table)}
    assert not found["$130"].ok and found["$131"].ok


# ---- the real firmware ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def grbl_sim_binary(tmp_path_factory) -> Path:
    exe = build_grbl_sim(tmp_path_factory.mktemp("grbl-sim"))
    if exe is None:
        pytest.skip(f"grbl-sim cannot be built here (needs gcc, make, stdbuf and {SHARED_GRBL_SIM})")
    return exe


@pytest.mark.slow
@pytest.mark.parametrize("eeprom", ["EEPROM.rig.DAT", None])
def test_on_real_grbl_firmware_the_check_reads_its_version_and_settings(grbl_sim_binary, tmp_path, eeprom):
    bridge = GrblSimBridge(grbl_sim_binary, tmp_path / "fw", SHARED_GRBL_SIM / eeprom if eeprom else None)
    try:
        bridge.wait_booted()
        code, found = check(write_config(tmp_path, f"grbl://{bridge.port}"))
    finally:
        bridge.close()
    assert code == 3 or eeprom, found
    assert ("turntable", "firmware") in found, found  # not a refused connect
    assert found["turntable", "firmware"]["detail"].startswith("Grbl 1.1h (1.1h.20190830:)")
    motion = [f"${n}" for n in (100, 101, 110, 111, 120, 121)]
    if eeprom:  # the rig's own settings: every one matches the config
        assert all(found["turntable", item]["ok"] for item in motion + ["$20", "$22", "$130", "$131"])
    else:  # factory settings: refused, each named with the firmware's value
        assert found["turntable", "$100"]["detail"] == "250 (config expects 44.444)"
        assert not any(found["turntable", item]["ok"] for item in motion)


# ---- calibration -------------------------------------------------------------------------------
@pytest.mark.slow
def test_calibrate_writes_the_rig_model_where_the_config_says_and_process_reads_it_from_there(tmp_path):
    from test_poses import ELEVATIONS, make_scan

    from station.process.stage import station_rig_model

    config = tmp_path / "station.toml"
    config.write_text('rig_model = "models/rig.json"\n')
    scan, _ = make_scan(tmp_path / "scan", "speckled", azimuths=12, width=640)
    result = runner.invoke(app, ["process", str(scan.root), "--config", str(config)])
    assert result.exit_code == 2 and "rig.json: rig model file not found" in " ".join(result.output.split())
    assert not (scan.root / "stages" / "process.json").exists()

    result = runner.invoke(app, ["calibrate", str(scan.root), "--config", str(config), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout[result.stdout.index("{"):])
    assert report["rig_model"] == str(tmp_path / "models" / "rig.json") and report["views"] == 24
    assert report["residuals"]["axis_tilt_from_nominal_deg"] < 0.5  # the simulated rig's axis is the nominal one
    model = station_rig_model(scan, tmp_path / "models" / "rig.json")
    assert model.kind == "calibrated" and sorted(model.elevation_poses) == list(ELEVATIONS)


def test_calibrate_needs_somewhere_to_write_and_a_scan_made_by_station_scan(tmp_path):
    result = runner.invoke(app, ["calibrate", str(tmp_path)])
    assert result.exit_code == 2 and "give --out" in result.output
    result = runner.invoke(app, ["calibrate", str(tmp_path), "--out", str(tmp_path / "m.json")])
    assert result.exit_code == 2 and "no rig and plan recorded" in " ".join(result.output.split())
