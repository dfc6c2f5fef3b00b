"""`station scan` from the operator's side: exit codes and messages for bad input and absent hardware."""

import json

from typer.testing import CliRunner

from sim.grbl_links import NmeaDevice, attach
from station.cli import app

runner = CliRunner()


def test_scan_without_a_rig_is_a_usage_error():
    result = runner.invoke(app, ["scan", "--out", "x"])
    assert result.exit_code == 2
    assert "--sim" in result.output


def test_an_odd_sensor_size_is_refused_with_the_reason(tmp_path):
    result = runner.invoke(app, ["scan", "--sim", "--out", str(tmp_path / "s"), "--size", "33x24"])
    assert result.exit_code == 2
    assert "even" in result.output


def test_a_missing_turntable_port_is_a_device_fault(tmp_path):
    result = runner.invoke(app, ["scan", "--port", str(tmp_path / "ttyNOPE"), "--out", str(tmp_path / "s")])
    assert result.exit_code == 3
    assert "ttyNOPE" in result.output


def test_a_device_that_is_not_grbl_is_a_device_fault_naming_the_port(tmp_path):
    with attach(NmeaDevice(), "url") as fake:
        result = runner.invoke(app, ["scan", "--port", fake.port, "--camera", "sim", "--out", str(tmp_path / "s")])
    assert result.exit_code == 3
    assert fake.port in result.output


def test_a_small_simulated_scan_reports_its_frames_as_json(tmp_path):
    result = runner.invoke(
        app, ["scan", "--sim", "--out", str(tmp_path / "s"), "--elevations", "1", "--azimuths", "3",
              "--size", "64x48", "--time-scale", "0.01", "--json"],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout[result.stdout.index("{"):])
    assert report["frames"] == 4 and report["shot_now"] == 4
