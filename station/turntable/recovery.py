"""Recovery policy: reconnect, then re-establish where the table is before any further move.

A collaborator of `Turntable` that uses only its public interface (`exclusive`, `reconnect`,
`counter_loss`, `last_seen`, `rehome`, `unlock`, `reference_to`, `resync`, `status`).
Policy, in order:
1. Reconnect. A vanished port (SerialException/OSError/EOF) is reopened by the same name, retrying
   until `reconnect_timeout_s`; a moving table is held (Hold:0) before the soft reset, then the
   banner, `$I`, `$$`, modal state and the G54 reference are checked as at connect. A port that
   never returns is DeviceDisconnectedError.
2. Re-establish position.
   - Homing enabled ($22=1): re-home ($H). The G54 reference in EEPROM stands on the switches, so
     the work position is exact again.
   - Homing disabled: unlock ($X) if in Alarm, then
     * the board kept its step counter (alarm, timeout or soft reset on a live port, checked by
       MPos lying where the driver last saw it or on the interrupted move's path): the work position
       is MPos - G54, exact unless a sudden halt (ALARM:1 hard limit, ALARM:3 reset while moving)
       may have lost steps;
     * the counter was lost (the board rebooted, or the USB link dropped, which power-cycles or
       DTR-resets a typical board): G10 L20 P1 declares the last position seen. It is exact when no
       move was running; otherwise the table stopped somewhere the driver never saw, `exact` is
       False, a warning is logged, and the session should re-shoot that view.
The interrupted move is not replayed: the session owns retries and issues it again.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from station.errors import DeviceDisconnectedError, DeviceError
from station.turntable.errors import NotGrblError

if TYPE_CHECKING:
    from station.turntable.grbl import Turntable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Recovery:
    """What recovery did: re-homed or re-referenced, and whether the position is exact."""

    rehomed: bool
    position: tuple[float, float]  # (turntable, tilt) degrees, work coordinates after recovery
    exact: bool  # False: restored from the last report seen while a move was cut short


class TurntableRecovery:
    """Runs the module's policy on one turntable, with no action running."""

    def __init__(self, table: Turntable) -> None:
        self.table = table

    def run(self) -> Recovery:
        table = self.table
        with table.exclusive():
            last_seen = table.last_seen
            self._reconnect()
            if table.homing_enabled:
                position = table.rehome()
                return Recovery(rehomed=True, position=position, exact=True)
            if table.status().state == "Alarm":
                table.unlock()
            loss = table.counter_loss
            if loss == "none":
                position, exact = table.resync(), table.position_exact
                if not exact:
                    log.warning("turntable on %s: position %s is not exact (a sudden halt: reset or hard "
                                "limit while moving); enable homing ($22=1) to re-reference", table.port, position)
            else:
                exact = loss == "at_rest"
                position = table.reference_to(last_seen, exact=exact)
            return Recovery(rehomed=False, position=position, exact=exact)

    def _reconnect(self) -> None:
        table = self.table
        deadline = time.monotonic() + table.config.reconnect_timeout_s
        while True:
            try:
                table.reconnect()
                return
            except NotGrblError:
                raise
            except DeviceError as exc:
                table.close()
                if time.monotonic() >= deadline:
                    raise DeviceDisconnectedError(f"turntable on {table.port} did not come back within "
                                                  f"{table.config.reconnect_timeout_s:g} s: {exc}") from exc
                time.sleep(0.1)
