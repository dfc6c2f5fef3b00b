"""Recovery policy: reconnect, then re-establish where the table is before any further move.

Policy (what `Turntable.recover()` does, in order):
1. Reconnect. If the port vanished (SerialException/OSError/EOF) it is reopened by the same name,
   retrying until `reconnect_timeout_s`; then a soft reset (0x18), the banner, `$I` and the `$$`
   check run as at connect. A port that never returns is DeviceDisconnectedError.
2. Re-establish position.
   - Homing enabled ($22=1): re-home ($H). Machine coordinates are exact again; the old work offset
     is restored with G92, the turntable coordinate put back on the turn it was on (same angle
     mod 360), so an unwrapped (continuous) scan carries on.
   - Homing disabled: unlock ($X) if in Alarm, then restore the work position with G92:
     * the board kept its step counter (alarm or soft reset on a live port): work = MPos - old
       offset, exact;
     * the counter was lost (the board rebooted: banner mid-session, or the USB link dropped,
       which power-cycles or DTR-resets a typical board): the last position the driver saw is
       restored. It is exact when no move was running; otherwise the table stopped somewhere the
       driver never saw, `Recovery.exact` is False, and the session should re-shoot that view.
3. Verify by a fresh status report that the work position is the one intended, else DeviceError.
The interrupted move is not replayed: the session owns retries and issues it again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from station.errors import DeviceDisconnectedError, DeviceError
from station.turntable.errors import NotGrblError

if TYPE_CHECKING:
    from station.turntable.grbl import Turntable


@dataclass(frozen=True)
class Recovery:
    """What recover() did: re-homed or restored a work position, and whether that is exact."""

    rehomed: bool
    position: tuple[float, float]  # (turntable, tilt) degrees, work coordinates after recovery
    exact: bool  # False: restored from the last report seen while a move was cut short


def _reconnect(table: Turntable) -> None:
    cfg = table.config
    deadline = time.monotonic() + cfg.reconnect_timeout_s
    while True:
        try:
            if table._proto is None:
                table._open()
            table._identify()
            return
        except NotGrblError:
            raise
        except DeviceError as exc:
            table.close()
            table._lose_counter()
            if time.monotonic() >= deadline:
                raise DeviceDisconnectedError(
                    f"turntable on {table.port} did not come back within {cfg.reconnect_timeout_s:g} s: {exc}") from exc
            time.sleep(0.1)


def recover(table: Turntable) -> Recovery:
    """Apply the module's policy; returns what was done. Call with no action running."""
    with table._io:
        old_wco = table._wco or (0.0,) * (table._axis + 1)
        last_seen = table._last_seen
        _reconnect(table)
        proto, cfg, axis = table._p, table.config, table._axis
        timeout = cfg.reply_timeout_s
        lost, mid_move = table._counter_lost, table._counter_lost_mid_move
        if table.homing_enabled:
            table._home_locked()
            mpos = proto.query_status(timeout).machine_position(table._wco)
            work_x = mpos[0] - old_wco[0]
            work_x += 360.0 * round((last_seen[0] - work_x) / 360.0)
            work = (work_x, mpos[axis] - old_wco[axis])
            exact = True
        else:
            if proto.query_status(timeout).state == "Alarm":
                proto.command("$X", timeout)
            mpos = proto.query_status(timeout).machine_position(table._wco)
            if lost:
                work, exact = last_seen, not mid_move
            else:
                work, exact = (mpos[0] - old_wco[0], mpos[axis] - old_wco[axis]), True
        proto.command(f"G92 X{work[0]:.4f} {cfg.tilt_axis}{work[1]:.4f}", timeout)
        table._read_wco()
        status = proto.query_status(timeout)
        if not table._at(status, work):
            raise DeviceError(f"turntable on {table.port}: after recovery the work position is "
                              f"{table._work(status)}, expected {work}")
        table._known = table._last_seen = table._work(status)
        table._counter_lost = table._counter_lost_mid_move = False
        return Recovery(rehomed=table.homing_enabled, position=table._known, exact=exact)
