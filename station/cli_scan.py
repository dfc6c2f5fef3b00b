"""The CLI's scan wiring: builds (or opens) the devices, runs the session, closes everything.

The only place in `station/` besides the CLI that reaches into `sim/`, and only when the
operator asked for the simulated rig (`--sim` or `--camera sim`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from station.capture.plan import ScanPlan, default_elevations
from station.capture.session import Operator, OperatorAction, ScanControl, ScanSession, ScanSummary
from station.errors import BadInputError, DeviceError
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder

Progress = Callable[[int, int, str], None]


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


def run_hardware_scan(
    out: Path, port: str, camera: str, elevations: int, azimuths: int, size: tuple[int, int], progress: Progress,
    control: ScanControl | None = None, operator: Operator | None = None,
) -> ScanSummary:
    """Scan with a real turntable, and a real PTP camera (or the simulated one for bench tests).

    The dashboard passes its own `control` (pause/cancel) and `operator` (prompts on the page).
    """
    from station.capture.ptp import open_ptp_camera
    from station.capture.still import PtpStillCamera
    from station.turntable.grbl import Turntable

    rig_geometry = RigGeometry().scaled(*size)
    turntable = Turntable.connect(port)
    try:
        if camera == "usb":
            ptp = open_ptp_camera()
        elif camera == "sim":
            from sim.rig import make_stone
            from sim.ptp_camera import SimPtpCamera
            from sim.scene import World, frame_source
            from sim.sensor import SensorModel
            from sim.usb_backend import SimUsbBackend

            world = World(make_stone(None), rig=rig_geometry)
            ptp = open_ptp_camera(backend=SimUsbBackend(SimPtpCamera(frame_source(world, turntable.position, SensorModel(), 0))))
        else:
            raise BadInputError(f"--camera {camera!r}: expected 'usb' or 'sim'")
        try:
            session = ScanSession(
                ScanFolder(out), _plan(elevations, azimuths), rig_geometry, turntable, PtpStillCamera(ptp),
                operator or TerminalOperator(), stone_id=out.name, progress=progress, control=control,
            )
            return session.run()
        finally:
            ptp.close()
    except OSError as exc:
        if isinstance(exc, DeviceError):
            raise
        raise DeviceError(f"scan on {port}: {exc}") from exc
    finally:
        turntable.close()
