"""The CLI's scan wiring: opens the rig the config describes, runs the session, closes everything.

The only place in `station/` besides the CLI that reaches into `sim/`: `run_sim_scan` for
`--sim`, and the `sim://` camera and bare `fakegrbl://` board it registers with the rig
assembly (station/capture/rig.py), imported only when such a URL is opened.
"""

from __future__ import annotations

import logging
import sys
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path
from typing import Callable

from station.capture.plan import ScanPlan, default_elevations
from station.capture.rig import CameraContext, RigCamera, open_rig, register_camera_scheme, register_turntable_scheme
from station.capture.session import Operator, OperatorAction, ScanControl, ScanSession, ScanSummary
from station.capture.still import CameraSettings
from station.config import StationConfig
from station.errors import BadInputError, DeviceError
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder
from station.turntable.grbl import Turntable, TurntableConfig

log = logging.getLogger(__name__)
Progress = Callable[[int, int, str], None]
SIM_TIME_SCALE = 0.05  # simulated motion and exposure run this much faster than real time


class TerminalOperator:
    """Asks the person at the station to act, and waits for Enter."""

    def request(self, action: OperatorAction, message: str) -> None:
        if not sys.stdin.isatty():
            raise BadInputError(f"operator action needed ({action}): {message} No terminal to ask on; run interactively.")
        input(f"{message} Press Enter when done. ")


def _plan(elevations: int, azimuths: int) -> ScanPlan:
    return ScanPlan(elevations_deg=default_elevations(elevations), azimuths=azimuths)


def run_sim_scan(
    out: Path, stone: str | None, elevations: int, azimuths: int, size: tuple[int, int], time_scale: float, progress: Progress,
    control: ScanControl | None = None,
) -> ScanSummary:
    """Scan on the simulated rig and write sim_truth/ beside the scan (`control`: the dashboard's pause/cancel)."""
    from sim.rig import build_sim_rig, make_stone

    rig_geometry = RigGeometry().scaled(*size)
    stone_model = make_stone(stone)
    scan = ScanFolder(out)
    with build_sim_rig(stone_model, rig_geometry, time_scale=time_scale) as rig:
        session = ScanSession(
            scan, _plan(elevations, azimuths), rig_geometry, rig.turntable, rig.camera, rig.operator,
            stone_id=stone_model.name, progress=progress, control=control,
        )
        summary = session.run()
        rig.write_truth(scan)
    return summary


def _open_sim_camera(url: str, context: CameraContext) -> RigCamera:
    """`sim://[STONE]`: the simulated PTP camera rendering a stone at the turntable's real position."""
    from sim.ptp_camera import SimPtpCamera
    from sim.rig import make_stone
    from sim.scene import World, frame_source
    from sim.sensor import SensorModel
    from sim.usb_backend import SimUsbBackend
    from station.capture.ptp import open_ptp_camera
    from station.capture.still import PtpStillCamera

    if context.turntable is None:
        raise BadInputError(f"camera URL {url!r}: the simulated camera needs a turntable to render from")
    world = World(make_stone(url[len("sim://"):] or None), rig=context.rig)
    device = SimPtpCamera(frame_source(world, context.turntable.position, SensorModel(), 0), time_scale=SIM_TIME_SCALE)
    return PtpStillCamera(open_ptp_camera(backend=SimUsbBackend(device)))


def _open_fake_board(url: str, config: TurntableConfig, stack: ExitStack) -> Turntable:
    """`fakegrbl://NAME` opens a board registered under NAME; a bare `fakegrbl://` starts one set up as `config` says."""
    from sim.grbl_links import register_url_scheme, start_fake_turntable

    register_url_scheme()
    if url.rstrip("/") != "fakegrbl:":
        return Turntable.connect(url, config)
    tilt = {"Y": 1, "A": 3}[config.tilt_axis]
    settings = {}
    for j, axis in enumerate((0, tilt)):
        settings |= {100 + axis: config.steps_per_deg[j], 110 + axis: config.max_rate_deg_min[j],
                     120 + axis: config.accel_deg_s2[j]}
    board = stack.enter_context(start_fake_turntable(time_scale=SIM_TIME_SCALE, settings=settings))
    return Turntable.connect(board.port, config)


def register_sim_schemes() -> None:
    """Let the rig assembly open `sim://` cameras and `fakegrbl://` boards; sim/ is imported only when one is opened."""
    register_camera_scheme("sim", _open_sim_camera)
    register_turntable_scheme("fakegrbl", _open_fake_board)


def run_hardware_scan(
    out: Path, config: StationConfig, progress: Progress, control: ScanControl | None = None,
    operator: Operator | None = None,
) -> ScanSummary:
    """Scan with the rig `config` describes (the camera may be the simulated one, for bench tests).

    The camera's settings are applied first and read back, so scan.json and the manifest record
    the exposure it really uses. The dashboard passes its own `control` (pause/cancel) and
    `operator` (prompts on the page).
    """
    register_sim_schemes()
    table = config.turntable
    try:
        with open_rig(table.port, table.driver_config(), config.camera.resolved_url, config.rig.geometry()) as rig:
            cam = config.camera
            used = rig.camera.apply(CameraSettings(cam.exposure_s, cam.iso, cam.aperture))
            if used.unverified:
                log.warning("%s: set on the camera body, not by the station: %s", config.source, ", ".join(used.unverified))
            plan = replace(config.scan_plan(), exposure_s=used.exposure_s, iso=used.iso)
            session = ScanSession(
                ScanFolder(out), plan, rig.geometry, rig.turntable, rig.camera, operator or TerminalOperator(),
                stone_id=out.name, progress=progress, control=control,
            )
            return session.run()
    except OSError as exc:
        if isinstance(exc, DeviceError):
            raise
        raise DeviceError(f"scan on {table.port}: {exc}") from exc
