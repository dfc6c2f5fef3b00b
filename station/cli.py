"""The `station` command: thin wrappers that parse, call one function, and print the outcome."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from station import __version__
from station.cli_support import configure_logging, emit, err_console, exits_on_station_errors, progress_reporter
from station.errors import BadInputError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Turntable capture-to-asset station.")


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging.")) -> None:
    configure_logging(verbose)


@app.command()
def version() -> None:
    """Print the software version."""
    typer.echo(__version__)


def _parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError as exc:
        raise BadInputError(f"--size {size!r}: expected WIDTHxHEIGHT, e.g. 320x240") from exc
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise BadInputError(f"--size {size!r}: both sides must be even and at least 16 pixels (Bayer 2x2 cells)")
    return width, height


@app.command()
@exits_on_station_errors
def scan(
    out: Path = typer.Option(..., "--out", help="Scan folder to create or resume."),
    sim: bool = typer.Option(False, "--sim", help="Scan on the simulated rig."),
    stone: Optional[str] = typer.Option(None, "--stone", help="Simulated stone: mesh path, seed, or look:seed."),
    port: Optional[str] = typer.Option(None, "--port", help="Turntable serial device or pyserial URL."),
    camera: str = typer.Option("usb", "--camera", help="usb (PTP camera) or sim (simulated camera)."),
    elevations: int = typer.Option(6, "--elevations", min=1),
    azimuths: int = typer.Option(40, "--azimuths", min=1),
    size: str = typer.Option("320x240", "--size", help="Simulated sensor size WxH."),
    time_scale: float = typer.Option(0.05, "--time-scale", help="Simulated motion/exposure time factor."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Shoot (or resume) a 6x40 hemisphere scan: plates first, then every shot; nothing is ever re-shot twice."""
    from station.cli_scan import run_hardware_scan, run_sim_scan

    width, height = _parse_size(size)
    started = time.monotonic()
    with progress_reporter("scan") as progress:
        if sim:
            summary = run_sim_scan(out, stone, elevations, azimuths, (width, height), time_scale, progress)
        elif port:
            summary = run_hardware_scan(out, port, camera, elevations, azimuths, (width, height), progress)
        else:
            raise BadInputError("scan: give --sim, or --port DEVICE for a real turntable")
    result = {
        "scan": str(out),
        "frames": summary.total,
        "shot_now": len(summary.shot),
        "verified_from_before": len(summary.skipped_verified),
        "reshot_corrupt": len(summary.reshot_corrupt),
        "recoveries": summary.recoveries,
        "seconds": round(time.monotonic() - started, 2),
    }
    emit(result, as_json, lambda r: err_console.print(
        f"scan {r['scan']}: {r['frames']} frames ({r['shot_now']} shot now, {r['verified_from_before']} kept) in {r['seconds']} s"
    ))


@app.command()
@exits_on_station_errors
def demo(
    out: Path = typer.Option(Path("demo-out"), "--out", help="Folder for the demo scan and its asset."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """The main job on embedded defaults: a simulated rig scans a stone, then every later stage runs."""
    from station.cli_scan import run_sim_scan

    scan_dir = out / "scan"
    started = time.monotonic()
    with progress_reporter("scan") as progress:
        summary = run_sim_scan(scan_dir, None, 6, 40, (320, 240), 0.05, progress)
    result = {"scan": str(scan_dir), "frames": summary.total, "seconds": round(time.monotonic() - started, 1)}
    emit(result, as_json, lambda r: err_console.print(f"demo: scanned {r['frames']} frames into {r['scan']} in {r['seconds']} s"))
