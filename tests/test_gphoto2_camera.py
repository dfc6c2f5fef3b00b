"""The libgphoto2 backend against libgphoto2's own virtual camera, shipped in the python-gphoto2 wheel.

libgphoto2 reads IOLIBS and VCAMERADIR once, when `gphoto2` is imported, so each case runs in a child
process. The virtual camera (a Nikon D750 on the real ptp2 camlib) serves the bytes of the first file in
VCAMERADIR whose name contains ".jpg": a DNG named shot.jpg.dng stands in for the raw a body returns.
"""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from sim.dng import dng_bytes
from sim.sensor import SensorModel
from station.capture.gphoto2_camera import nearest_choice, parse_fnumber, parse_seconds
from station.errors import BadInputError

GPHOTO2 = importlib.util.find_spec("gphoto2")
pytestmark = [pytest.mark.skipif(GPHOTO2 is None, reason="python-gphoto2 is not installed"),
              pytest.mark.no_kernels]
RGGB_ENTRY = bytes.fromhex("8e820100040000000001 0102".replace(" ", ""))  # CFAPattern: BYTE x4 = 0 1 1 2
GRBG_ENTRY = RGGB_ENTRY[:8] + bytes([1, 0, 2, 1])


def grbg_dng(width: int = 64, height: int = 48) -> bytes:
    """A DNG whose sensor is GRBG, so a backend assuming RGGB is caught."""
    mosaic = (np.arange(width * height, dtype=np.uint16).reshape(height, width) % 1000 + 600).astype(np.uint16)
    data = dng_bytes(mosaic, SensorModel())
    assert data.count(RGGB_ENTRY) == 1
    return data.replace(RGGB_ENTRY, GRBG_ENTRY)


@pytest.fixture
def vcamera(tmp_path):
    """A folder for the virtual camera holding one raw, and the environment that points libgphoto2 at it."""
    folder = tmp_path / "vcamera"
    folder.mkdir()
    raw = folder / "shot.jpg.dng"
    raw.write_bytes(grbg_dng())
    package = Path(GPHOTO2.origin).parent
    env = {**os.environ, "IOLIBS": str(package / "libgphoto2" / "vusb"), "VCAMERADIR": str(folder)}
    return raw, env


def write_config(tmp_path: Path, exposure_s: float = 0.02, extra: str = "") -> Path:
    path = tmp_path / "station.toml"
    path.write_text(f"""
[rig]
width = 64
height = 48
focal_px = 112.0
[turntable]
port = "fakegrbl://"
[camera]
backend = "gphoto2"
exposure_s = {exposure_s}
iso = 200
aperture = 8.0
{extra}
[plan]
elevations = 1
azimuths = 3
""")
    return path


SCAN = """
import json, sys
from pathlib import Path
from station.cli_scan import run_hardware_scan
from station.config import load_config
from station.errors import StationError

raw, stop_after = Path(sys.argv[3]), int(sys.argv[4])

class Operator:
    def request(self, action, message):
        pass

def progress(done, total, what):
    if done == stop_after:  # the camera stops delivering from here on
        raw.rename(raw.with_suffix(".gone"))

try:
    summary = run_hardware_scan(Path(sys.argv[2]), load_config(Path(sys.argv[1])), progress, operator=Operator())
except StationError as exc:
    print(json.dumps({"error": str(exc), "exit_code": exc.exit_code}))
else:
    print(json.dumps({"shot": summary.shot, "kept": summary.skipped_verified}))
"""


def run_scan(tmp_path: Path, env: dict, raw: Path, stop_after: int = -1) -> dict:
    done = subprocess.run([sys.executable, "-c", SCAN, str(write_config(tmp_path)), str(tmp_path / "scan"), str(raw),
                           str(stop_after)], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_widget_strings_of_several_vendors_parse_and_the_nearest_step_is_chosen():
    assert parse_seconds("1/30") == pytest.approx(1 / 30) and parse_seconds("0.0333s") == pytest.approx(0.0333)
    assert parse_seconds('2"') == 2.0 and parse_seconds("bulb") is None and parse_seconds("Auto") is None
    assert parse_fnumber("f/5.6") == 5.6 and parse_fnumber("8") == 8.0 and parse_fnumber("implicit auto") is None
    assert nearest_choice(["1/25", "1/30", "1/40", "bulb"], 1 / 32, parse_seconds, "exposure", "cam") == "1/30"
    with pytest.raises(BadInputError, match="nearest '0.0500s'"):
        nearest_choice(["0.0500s", "0.0200s"], 1 / 30, parse_seconds, "exposure", "cam")


def test_rig_check_detects_the_virtual_camera_and_reads_its_cfa_from_the_raw(tmp_path, vcamera):
    raw, env = vcamera
    done = subprocess.run([sys.executable, "-m", "station", "rig", "check", "--config", str(write_config(tmp_path)),
                           "--json"], env=env, capture_output=True, text=True, timeout=300)
    report = json.loads(done.stdout)
    found = {(f["part"], f["item"]): f for f in report["findings"]}
    assert done.returncode == 0, found
    assert found["camera", "model"]["detail"].startswith("GP Nikon DSC D750")
    assert found["camera", "battery"]["detail"] == "50%"
    assert found["camera", "storage"]["detail"].endswith("MB free")
    # No iso widget on this body: said clearly, not a crash; shutter speed and f-number are set and read back.
    assert found["camera", "settings"]["detail"] == "0.02 s, ISO 200, f/8; set on the body, not by the station: iso"
    assert found["camera", "test shot"]["detail"] == "64x48 dng, CFA GRBG"
    assert "has no 'iso' setting through libgphoto2" in done.stderr


def test_an_exposure_the_body_does_not_offer_is_refused_naming_the_nearest(tmp_path, vcamera):
    raw, env = vcamera
    done = subprocess.run([sys.executable, "-m", "station", "rig", "check", "--config",
                           str(write_config(tmp_path, exposure_s=1 / 30)), "--json"],
                          env=env, capture_output=True, text=True, timeout=300)
    found = {(f["part"], f["item"]): f for f in json.loads(done.stdout)["findings"]}
    assert done.returncode == 3
    assert "exposure time (s) 0.0333333 is not offered" in found["camera", "test shot"]["detail"]


def test_a_small_scan_downloads_every_raw_byte_for_byte_with_the_exposure_the_camera_used(tmp_path, vcamera):
    raw, env = vcamera
    result = run_scan(tmp_path, env, raw)
    assert result["shot"] == ["raw/plate_e0.dng", "raw/e0_a000.dng", "raw/e0_a001.dng", "raw/e0_a002.dng"]
    for name in result["shot"]:
        assert (tmp_path / "scan" / name).read_bytes() == raw.read_bytes()
    assert not [p for p in (tmp_path / "scan" / "raw").iterdir() if p.name.startswith(".")]  # no temp file left
    entries = [json.loads(line) for line in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    assert {e["exposure_s"] for e in entries} == {0.02}


def test_a_camera_lost_mid_scan_stops_it_keeping_every_frame_and_the_next_run_resumes(tmp_path, vcamera):
    raw, env = vcamera
    stopped = run_scan(tmp_path, env, raw, stop_after=2)
    assert stopped["exit_code"] == 3 and "camera failed on raw/e0_a001.dng" in stopped["error"]
    listed = [json.loads(line)["file"] for line in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    assert listed == ["raw/plate_e0.dng", "raw/e0_a000.dng"]
    raw.with_suffix(".gone").rename(raw)  # the camera is back
    resumed = run_scan(tmp_path, env, raw)
    assert resumed["kept"] == listed and resumed["shot"] == ["raw/e0_a001.dng", "raw/e0_a002.dng"]


RECONNECT = """
import json
from station.capture.gphoto2_camera import open_gphoto2_camera
from station.capture.still import CameraSettings

camera = open_gphoto2_camera()
used = camera.apply(CameraSettings(0.1, 100, 5.6))
first = camera.trigger().download()
camera.close()  # the connection is gone; the next capture opens the body again and restores its settings
second = camera.trigger().download()
shutter = camera.value("shutterspeed")
camera.close()
print(json.dumps({"port": camera.port, "sizes": [len(first), len(second)], "shutter": shutter,
                  "used": [used.exposure_s, used.aperture]}))
"""


def test_a_camera_that_went_away_is_opened_again_with_its_settings(vcamera):
    raw, env = vcamera
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(RECONNECT)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["port"] == "usb:001,001" and result["sizes"] == [raw.stat().st_size] * 2
    assert result["shutter"] == "0.1000s" and result["used"] == [0.1, 5.6]


def test_a_camera_url_naming_another_port_fails_listing_the_cameras_detected(tmp_path, vcamera):
    raw, env = vcamera
    config = write_config(tmp_path, extra='url = "gphoto2://usb:009,009"')
    done = subprocess.run([sys.executable, "-m", "station", "rig", "check", "--config", str(config), "--json"],
                          env=env, capture_output=True, text=True, timeout=300)
    found = {(f["part"], f["item"]): f for f in json.loads(done.stdout)["findings"]}
    assert done.returncode == 3
    assert "no libgphoto2 camera on usb:009,009" in found["camera", "connect"]["detail"]
    assert "detected: Nikon DSC D750 on usb:001,001" in found["camera", "connect"]["detail"]
