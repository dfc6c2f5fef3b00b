"""station.toml: the documented example loads, bad keys and values are named, flags override, the rig comes from it."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from station.cli import app
from station.cli_scan import run_hardware_scan
from station.config import ConfigError, load_config, parse_config
from station.errors import BadInputError

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "station.example.toml"
runner = CliRunner()


class Operator:
    def __init__(self):
        self.asked = []

    def request(self, action, message):
        self.asked.append(action)


def write(tmp_path, text):
    path = tmp_path / "station.toml"
    path.write_text(text)
    return path


def test_the_documented_example_loads_with_every_section_it_shows():
    config = load_config(EXAMPLE)
    assert config.turntable.port == "grbl:///dev/ttyUSB0"
    assert config.camera.backend == "gphoto2" and config.camera.resolved_url == "gphoto2://"
    assert config.turntable.driver_config().steps_per_deg == (44.444, 44.444)
    assert config.scan_plan().azimuths == 40 and len(config.scan_plan().elevations_deg) == 6
    assert config.rig_model_path() == EXAMPLE.parent / "rig-model.json"


def test_expected_settings_follow_the_tilt_axis_letter():
    table = parse_config({"turntable": {"tilt_axis": "A", "steps_per_deg": [10.0, 20.0]}}, "t.toml").turntable
    assert table.expected_settings()[103] == 20.0 and 101 not in table.expected_settings()
    assert table.expected_settings()[20] == 0.0 and table.expected_settings()[130] == 720.0


@pytest.mark.parametrize("text, named", [
    ("[turntable]\nstpes_per_deg = [1.0, 2.0]\n", "turntable.stpes_per_deg: unknown key"),
    ("[camera]\niso = \"fast\"\n", "camera.iso"),
    ("[camera]\nbackend = \"usb\"\n", "camera.backend"),
    ("[turntable]\nsteps_per_deg = [1.0]\n", "turntable.steps_per_deg[1]"),
    ("[turntable]\nsteps_per_deg = [0.0, 1.0]\n", "turntable.steps_per_deg must be positive"),
    ("[rig]\nwidth = 33\n", "rig.width and height must be even"),
    ("[plan]\nelevations_deg = [95.0]\n", "elevations must lie in (-90, 90]"),
    ("[cameras]\niso = 100\n", "cameras: unknown key"),
    ("source = \"x\"\n", "unknown key 'source'"),
    ("[camera\n", "not valid TOML"),
])
def test_a_bad_key_or_value_is_refused_naming_the_file_and_the_key(tmp_path, text, named):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(path) in str(caught.value) and named in str(caught.value)


def test_a_missing_config_file_is_a_usage_error_from_the_cli(tmp_path):
    result = runner.invoke(app, ["scan", "--config", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "nope.toml" in result.output and "not found" in result.output


def test_flags_override_the_file(tmp_path):
    config = load_config(write(tmp_path, "[turntable]\nport = \"grbl:///dev/ttyACM0\"\n[plan]\nelevations_deg = [20.0]\n"))
    moved = config.with_overrides(port="fakegrbl://", camera="sim", elevations=2, azimuths=5)
    assert moved.turntable.port == "fakegrbl://" and moved.camera.resolved_url == "sim://"
    assert len(moved.scan_plan().elevations_deg) == 2 and moved.scan_plan().azimuths == 5
    assert config.with_overrides(camera="usb").camera.resolved_url == "ptp://usb"
    assert config.with_overrides(camera="gphoto2://usb:001,004").camera.resolved_url == "gphoto2://usb:001,004"
    with pytest.raises(BadInputError):
        config.with_overrides(camera="webcam")


def test_a_hardware_scan_takes_its_geometry_plan_and_exposure_from_the_config(tmp_path):
    config = load_config(write(tmp_path, """
[rig]
width = 64
height = 48
focal_px = 112.0
orbit_radius_m = 0.5
[turntable]
port = "fakegrbl://"
[camera]
backend = "sim"
exposure_s = 0.02
iso = 200
[plan]
elevations_deg = [30.0]
azimuths = 2
"""))
    operator = Operator()
    summary = run_hardware_scan(tmp_path / "scan", config, lambda done, total, what: None, operator=operator)
    assert summary.total == 3 and operator.asked == ["clear_turntable", "place_stone"]
    record = json.loads((tmp_path / "scan" / "scan.json").read_text())
    assert record["rig"] == {"orbit_radius_m": 0.5, "aim_height_m": 0.04, "width": 64, "height": 48, "focal_px": 112.0}
    assert record["plan"]["elevations_deg"] == [30.0] and record["plan"]["azimuths"] == 2
    assert record["plan"]["exposure_s"] == 0.02 and record["plan"]["iso"] == 200  # as the camera reads them back
    lines = [json.loads(line) for line in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    assert {(e["exposure_s"], e["iso"]) for e in lines} == {(0.02, 200)}


def test_the_exposure_recorded_is_the_step_the_camera_really_uses(tmp_path):
    config = parse_config({"rig": {"width": 64, "height": 48, "focal_px": 112.0}, "turntable": {"port": "fakegrbl://"},
                           "camera": {"backend": "sim", "exposure_s": 1.0 / 30.0}, "plan": {"elevations": 1, "azimuths": 1}},
                          "t.toml")
    run_hardware_scan(tmp_path / "scan", config, lambda done, total, what: None, operator=Operator())
    entry = json.loads((tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()[0])
    assert entry["exposure_s"] == 0.0333  # the simulated body's 0.1 ms step, not the 0.03333... asked for
