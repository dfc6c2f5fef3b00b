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


def test_nothing_in_station_imports_sim_except_the_cli_scan_wiring():
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "station"
    importers = set()
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            if any(n == "sim" or n.startswith("sim.") for n in names):
                importers.add(path.relative_to(root.parent).as_posix())
    assert importers == {"station/cli_scan.py"}


def test_rig_urls_name_what_is_wrong(tmp_path):
    from contextlib import ExitStack

    import pytest

    from station.capture.rig import CameraContext, open_camera, open_turntable
    from station.errors import BadInputError
    from station.rig_geometry import RigGeometry
    from station.turntable.grbl import TurntableConfig

    with ExitStack() as stack:
        context = CameraContext(RigGeometry(), None, stack)
        with pytest.raises(BadInputError, match="unknown scheme; expected one of gphoto2://, ptp://"):
            open_camera("webcam://0", context)
        with pytest.raises(BadInputError, match="vendor and product are hexadecimal"):
            open_camera("ptp://usb?vendor=canon", context)
        with pytest.raises(BadInputError, match="only ptp://usb"):
            open_camera("ptp://ip/192.168.0.2", context)
        with pytest.raises(BadInputError, match="grbl:///dev/ttyUSB0"):
            open_turntable("grbl://", TurntableConfig(), stack)
        with pytest.raises(BadInputError, match="no turntable"):
            open_turntable("", TurntableConfig(), stack)


def test_a_hardware_scan_from_the_cli_needs_a_config_or_a_port_and_names_a_bad_camera(tmp_path):
    result = runner.invoke(app, ["scan", "--port", "fakegrbl://", "--camera", "webcam", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--camera 'webcam'" in result.output
