"""`station serve`: the operator's dashboard, served on loopback unless a token guards it.

Thin: parse, build the app with `make_dashboard`, run uvicorn. Scans go through the same wiring as
`station scan` (station/cli_scan.py), which alone reaches into `sim/`, and only for `--sim` or
`--camera sim`. FastAPI and uvicorn are imported only when the command runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from station.cli_support import err_console, exits_on_station_errors, parse_size
from station.errors import BadInputError

if TYPE_CHECKING:
    from fastapi import FastAPI

    from station.serve.rig_control import ScanFunction


def _sim_scans(size: tuple[int, int], time_scale: float) -> ScanFunction:
    from station.cli_scan import run_sim_scan

    def scan(out, request, hooks):
        return run_sim_scan(out, request.stone, request.elevations, request.azimuths, size, time_scale, hooks.progress,
                            control=hooks.control)

    return scan


def _hardware_scans(device: str, camera: str, size: tuple[int, int]) -> ScanFunction:
    from station.cli_scan import run_hardware_scan
    from station.config import StationConfig

    def scan(out, request, hooks):
        config = StationConfig().with_overrides(port=device, camera=camera, elevations=request.elevations,
                                                azimuths=request.azimuths)
        return run_hardware_scan(out, config, hooks.progress, control=hooks.control, operator=hooks.operator)

    return scan


def make_dashboard(
    *,
    host: str,
    sim: bool,
    device: str | None,
    camera: str,
    queue: Path | None,
    out_dir: Path,
    size: tuple[int, int],
    time_scale: float,
    elevations: int,
    azimuths: int,
    token: str | None,
    poll_seconds: float = 1.0,
) -> FastAPI:
    """The dashboard app, wired to the simulated rig, a real one, or none (the queue view only)."""
    from station.serve.app import ServeConfig, create_app
    from station.serve.rig_control import ScanRunner
    from station.serve.scans import ScanCatalog

    if sim and device:
        raise BadInputError("serve: give --sim or --device DEVICE, not both")
    if camera not in ("usb", "sim"):
        raise BadInputError(f"--camera {camera!r}: expected 'usb' or 'sim'")
    if sim:
        runner = ScanRunner(_sim_scans(size, time_scale), out_dir, "simulated rig")
    elif device:
        runner = ScanRunner(_hardware_scans(device, camera, size), out_dir, f"turntable on {device}, {camera} camera")
    else:
        runner = ScanRunner(None, out_dir, "no rig (serve was started without --sim or --device)")
    catalog = ScanCatalog(queue, runner.folders)
    return create_app(runner, catalog, ServeConfig(host, token, elevations, azimuths, poll_seconds))


@exits_on_station_errors
def serve(
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on; anything but loopback needs a token."),
    token: Optional[str] = typer.Option(None, "--token", envvar="STATION_TOKEN", show_envvar=True,
                                        help="Shared secret the dashboard asks for (needed beyond loopback); "
                                             "prefer the STATION_TOKEN variable, a command line is visible to ps."),
    port: int = typer.Option(8000, "--port", help="HTTP port of the dashboard."),
    sim: bool = typer.Option(False, "--sim", help="Scan on the simulated rig."),
    port_device: Optional[str] = typer.Option(None, "--device", help="Turntable serial device or pyserial URL."),
    camera: str = typer.Option("usb", "--camera", help="With --device: usb (PTP camera) or sim (simulated camera)."),
    queue: Path = typer.Option(Path("station-queue.sqlite"), "--queue", envvar="STATION_QUEUE",  # as `station batch`
                               help="The overnight queue's SQLite file, to show its scans."),
    out_dir: Path = typer.Option(Path("scans"), "--out-dir", help="Folder for the scans started from the dashboard."),
    elevations: int = typer.Option(6, "--elevations", min=1, help="The start form's default."),
    azimuths: int = typer.Option(40, "--azimuths", min=1, help="The start form's default."),
    size: str = typer.Option("320x240", "--size", help="Simulated sensor size WxH."),
    time_scale: float = typer.Option(0.05, "--time-scale", help="Simulated motion/exposure time factor."),
) -> None:
    """The operator's dashboard: rig state, scan buttons with a live preview, the queue's verdicts and reports."""
    import uvicorn

    token = token or None
    app = make_dashboard(
        host=host, sim=sim, device=port_device, camera=camera, queue=queue, out_dir=out_dir, size=parse_size(size),
        time_scale=time_scale, elevations=elevations, azimuths=azimuths, token=token,
    )
    shown = f"[{host}]" if ":" in host else host
    err_console.print(f"dashboard on http://{shown}:{port}/" + ("#token=... (the --token value)" if token else ""))
    uvicorn.run(app, host=host, port=port, ws="none", access_log=False, log_level="info")
