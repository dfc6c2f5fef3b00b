"""`station rig check` and `station calibrate`: what an operator runs on a new rig before its first scan.

The check opens every device the config names and compares what they say with what the config
expects, then makes one small move and one test shot; each finding is a line with a verdict, and
any failed line makes the command exit non-zero with the reasons. Calibration turns one full
scan of a textured stone into the rig model that `station process` then reads through the config.
"""

from __future__ import annotations

import math
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from station.cli_support import emit, err_console, exits_on_station_errors
from station.errors import BadInputError, DeviceError, StationError

if TYPE_CHECKING:  # the devices' modules load only when a command runs: `station --help` stays quick
    from station.config import StationConfig, TurntableSection
    from station.turntable.grbl import Turntable

rig_app = typer.Typer(no_args_is_help=True, help="Check the rig the config describes.")
TRAVEL_SETTINGS = (130, 131, 133)  # max travel: the rig needs at least the configured value
TEST_MOVE_DEG = 5.0


class RigCheckFailedError(DeviceError):
    """`station rig check` found something that would spoil a scan; the message lists every reason."""


@dataclass(frozen=True)
class Finding:
    part: str  # "turntable" or "camera"
    item: str
    ok: bool
    detail: str


def compare_settings(settings: dict[int, float], table: TurntableSection, rel_tol: float = 1e-3) -> list[Finding]:
    """Every `$` setting the rig depends on, against the config: travel at least, the rest equal."""
    found = []
    for number, want in sorted(table.expected_settings().items()):
        have = settings.get(number)
        if have is None:
            found.append(Finding("turntable", f"${number}", False, f"missing (config expects {want:g})"))
        elif number in TRAVEL_SETTINGS:
            enforced = bool(settings.get(20))  # GRBL checks max travel only with soft limits on
            note = "" if enforced else "; soft limits off ($20=0), so the board does not enforce it"
            found.append(Finding("turntable", f"${number}", have >= want or not enforced,
                                 f"{have:g} (travel; config needs >= {want:g}{note})"))
        else:
            ok = abs(have - want) <= rel_tol * max(abs(want), 1.0)
            found.append(Finding("turntable", f"${number}", ok, f"{have:g} (config expects {want:g})"))
    return found


def _check_move(table: Turntable, limits: tuple[float, float]) -> Finding:
    angle, tilt = table.position()
    tilt = min(max(tilt, limits[0]), limits[1])
    target = (angle + TEST_MOVE_DEG) % 360.0
    table.move_to(target, tilt).wait()
    got = table.position()
    error = abs((got[0] - target + 180.0) % 360.0 - 180.0)
    table.move_to(angle % 360.0, tilt).wait()
    ok = error < 0.1 and abs(got[1] - tilt) < 0.1
    return Finding("turntable", "test move", ok, f"turned {TEST_MOVE_DEG:g} deg and back; reached {got[0] % 360.0:.3f} "
                   f"deg (target {target:.3f}), tilt {got[1]:.3f} deg")


def check_turntable(config: StationConfig, stack: ExitStack) -> tuple[list[Finding], Turntable | None]:
    """Firmware, settings against the config, travel, and one small move and back."""
    from station.capture.rig import open_turntable

    section = config.turntable
    # The driver refuses a board whose motion settings differ; the check reports every one instead.
    lenient = replace(section.driver_config(), settings_rel_tol=math.inf)
    try:
        table = open_turntable(section.port, lenient, stack)
    except StationError as exc:
        return [Finding("turntable", "connect", False, str(exc))], None
    info = table.info
    found = [Finding("turntable", "firmware", True, f"{info.flavour} {info.version} ({info.build or 'no $I build'}) "
                     f"on {section.port}")] if info else []
    found += compare_settings(info.settings if info else {}, section)
    try:
        found.append(_check_move(table, section.tilt_limits_deg))
    except StationError as exc:
        found.append(Finding("turntable", "test move", False, str(exc)))
    return found, table


def check_camera(config: StationConfig, table: Turntable | None, stack: ExitStack) -> list[Finding]:
    """Model, battery, storage and raw support, the exposure the camera takes, then one test shot."""
    from station.capture.rig import CameraContext, open_camera
    from station.capture.still import CameraSettings, inspect_raw

    cam, rig = config.camera, config.rig
    try:
        camera = open_camera(cam.resolved_url, CameraContext(rig.geometry(), table, stack))
        report = camera.report()
    except StationError as exc:
        return [Finding("camera", "connect", False, str(exc))]
    found = [Finding("camera", "model", True, f"{report.model} ({cam.resolved_url})"),
             Finding("camera", "battery", True, report.battery or "not reported"),
             Finding("camera", "storage", True, "not reported" if report.storage_free_mb is None
                     else f"{report.storage_free_mb:.0f} MB free"),
             Finding("camera", "raw formats", True, ", ".join(report.raw_formats) or "not reported")]
    found += [Finding("camera", "problem", False, p) for p in report.problems]
    try:
        used = camera.apply(CameraSettings(cam.exposure_s, cam.iso, cam.aperture))
        kept = f"; set on the body, not by the station: {', '.join(used.unverified)}" if used.unverified else ""
        found.append(Finding("camera", "settings", True, f"{used.exposure_s:g} s, ISO {used.iso}"
                             + (f", f/{used.aperture:g}" if used.aperture else "") + kept))
        shot = inspect_raw(camera.trigger().download(), f"test shot from {report.model}")
    except StationError as exc:
        return found + [Finding("camera", "test shot", False, str(exc))]
    size_ok = (shot.width, shot.height) == (rig.width, rig.height)
    format_ok = cam.raw_format in ("any", shot.format)
    found.append(Finding("camera", "test shot", size_ok and format_ok, f"{shot.width}x{shot.height} {shot.format}, CFA {shot.cfa}"
                         + ("" if size_ok else f"; rig.width and rig.height in {config.source} say {rig.width}x{rig.height}")
                         + ("" if format_ok else f"; camera.raw_format in {config.source} says {cam.raw_format}")))
    return found


def check_rig(config: StationConfig) -> list[Finding]:
    with ExitStack() as stack:
        found, table = check_turntable(config, stack)
        return found + check_camera(config, table, stack)


def _print_findings(report: dict) -> None:
    for f in report["findings"]:
        line = f"{'ok  ' if f['ok'] else 'FAIL'} {f['part']:9} {f['item']:12} {f['detail']}"
        err_console.print(line, highlight=False, markup=False, soft_wrap=True)


@rig_app.command("check")
@exits_on_station_errors
def rig_check(
    config: Optional[Path] = typer.Option(None, "--config", help="station.toml describing the rig."),
    port: Optional[str] = typer.Option(None, "--port", help="Turntable URL, overriding the config."),
    camera: Optional[str] = typer.Option(None, "--camera", help="Camera backend or URL, overriding the config."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Open the turntable and camera, compare them with the config, make one small move and one test shot."""
    from station.cli_scan import register_sim_schemes
    from station.config import load_config

    register_sim_schemes()
    settings = load_config(config).with_overrides(port=port, camera=camera)
    found = check_rig(settings)
    failed = [f for f in found if not f.ok]
    emit({"config": settings.source, "ok": not failed, "findings": [vars(f) for f in found]}, as_json, _print_findings)
    if failed:
        raise RigCheckFailedError("rig check failed: " + "; ".join(f"{f.part} {f.item}: {f.detail}" for f in failed))


@exits_on_station_errors
def calibrate(
    scan_dir: Path = typer.Argument(..., help="A full scan of a well-textured stone, shot on this rig."),
    config: Optional[Path] = typer.Option(None, "--config", help="station.toml; the model goes to its rig_model path."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write the rig model here instead."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Fit the rig model (turntable axis, camera pose per ring) to a free SfM run of one scan.

    The SfM run starts from the [rig] section's intrinsics and self-calibrates the lens (focal, principal
    point, k1, k2, p1, p2); the model keeps it, so later scans start from, and undistort with, this lens.
    """
    from station.config import load_config
    from station.process.develop_stage import develop_scan
    from station.process.poses import PoseSettings, calibrate_from_scan
    from station.process.stage import station_rig_model
    from station.scanfolder import ScanFolder

    target = out or load_config(config).rig_model_path()
    if target is None:
        raise BadInputError("calibrate: give --out, or a --config whose rig_model names where the model goes")
    scan = ScanFolder(scan_dir)
    nominal = station_rig_model(scan, None)
    if nominal is None:
        raise BadInputError(f"{scan.scan_json}: no rig and plan recorded; calibrate from a scan made by `station scan`")
    if not scan.images_dir.is_dir():
        develop_scan(scan)
    model, report = calibrate_from_scan(scan, PoseSettings(), nominal)
    model.save(target)
    result = {"rig_model": str(target), "views": len(report.registered), "residuals": model.residuals,
              "lens": report.lens}
    emit(result, as_json, lambda r: err_console.print(
        f"rig model written to {r['rig_model']} from {r['views']} views: " +
        ", ".join(f"{k} {v:.4g}" for k, v in r["residuals"].items())))
