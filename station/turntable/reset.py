"""What every soft reset needs around it: a still table before, checked settings and modal state after.

A reset of a moving table raises ALARM:3 and loses steps, so motion is held first. After a reset
GRBL runs its stored `$N` startup lines and restores its default parser state, so units, distance
and feed mode are set explicitly and read back with `$G`.
"""

from __future__ import annotations

import logging
import time

from station.errors import DeviceError, DeviceTimeoutError
from station.turntable.config import TurntableConfig
from station.turntable.errors import GrblSettingsError
from station.turntable.protocol import GrblProtocol
from station.turntable.status import MachineStatus

log = logging.getLogger(__name__)
MODAL_LINE = "G21 G90 G94 G17 G54"  # mm (here degrees), absolute, units/min: whatever `$N` lines set
_MODAL_WORDS = {"G21", "G90", "G94", "G54"}


def hold_until_still(proto: GrblProtocol, status: MachineStatus | None, config: TurntableConfig) -> None:
    """Feed hold (`!`) a table found moving and wait for Hold:0, so the reset after it keeps position."""
    if status is None or status.state not in ("Run", "Jog", "Hold"):
        return
    log.warning("turntable on %s was %s at connect; holding it before the reset", proto.port, status.state)
    proto.line.write(b"!")
    deadline = time.monotonic() + config.reply_timeout_s + config.motion_margin_s
    while not (status.state == "Hold" and status.substate == 0) and status.state != "Idle":
        if time.monotonic() > deadline:
            raise DeviceTimeoutError(f"turntable on {proto.port} did not come to rest (Hold:0) for a safe reset")
        time.sleep(1.0 / config.poll_hz)
        status = proto.query_status(config.reply_timeout_s)


def check_startup_echoes(echoed: tuple[str, ...], port: str) -> None:
    """`$N` lines run after every reset (`>G20:ok`): a failed one is refused, any other overridden."""
    for line in echoed:
        if not line.endswith(":ok"):
            raise DeviceError(f"turntable on {port}: its stored startup line failed ({line!r}); "
                              f"clear it with $N0= / $N1=")
        log.warning("turntable on %s ran its startup line %r after the reset; its modal state is overridden",
                    port, line)


def set_modal_state(proto: GrblProtocol, timeout_s: float) -> None:
    """Explicit units, distance and feed mode, no G92 offset; refused unless `$G` reads them back."""
    proto.command(MODAL_LINE, timeout_s)
    proto.command("G92.1", timeout_s)  # a startup line may have set a G92 offset
    modes = proto.command("$G", timeout_s)
    words = set(next((s[4:-1] for s in modes if s.startswith("[GC:")), "").split())
    if not _MODAL_WORDS <= words:
        raise DeviceError(f"turntable on {proto.port} did not take {MODAL_LINE!r}: parser state {modes!r}")


def check_settings(settings: dict[int, float], config: TurntableConfig, tilt_index: int, port: str) -> None:
    """`$$` against the rig's steps per degree, rates and accelerations; each mismatch is named."""
    expected: dict[int, tuple[float, str]] = {}
    for j, axis in enumerate((0, tilt_index)):
        expected[100 + axis] = (config.steps_per_deg[j], "steps/degree")
        expected[110 + axis] = (config.max_rate_deg_min[j], "degree/min max rate")
        expected[120 + axis] = (config.accel_deg_s2[j], "degree/s^2 acceleration")
    wrong = []
    for number, (want, unit) in expected.items():
        have = settings.get(number)
        if have is None:
            wrong.append(f"${number} missing (expected {want:g} {unit})")
        elif abs(have - want) > config.settings_rel_tol * abs(want):
            wrong.append(f"${number}={have:g} (expected {want:g} {unit})")
    if wrong:
        raise GrblSettingsError(f"turntable on {port} is configured differently from the rig: " + ", ".join(wrong))
