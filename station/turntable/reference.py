"""The position reference: GRBL's G54 work offset, read from `$#` and checked against status `WCO`.

Work position = MPos - WCO, and WCO = G54 + G92. G92 offsets vanish on every soft reset and the
driver resets at each connect, so the reference is G54 alone (set with G10 L20 P1): GRBL keeps it
in EEPROM, through resets, power cycles and restarts of `station`.
"""

from __future__ import annotations

from dataclasses import dataclass

from station.errors import DeviceError
from station.turntable.errors import ReferenceMismatchError
from station.turntable.protocol import GrblProtocol
from station.turntable.status import MachineStatus

_TOL = 2e-3  # `$#` and WCO are printed with 3 decimals


@dataclass(frozen=True)
class Reference:
    """Offsets as `$#` printed them, per axis in report order (X, Y, Z[, A...])."""

    g54: tuple[float, ...]
    g92: tuple[float, ...]

    @property
    def wco(self) -> tuple[float, ...]:
        return tuple(a + b for a, b in zip(self.g54, self.g92))

    def check(self, status: MachineStatus, port: str) -> None:
        """The report's WCO (when it carries one) must be the stored G54 with G92 cleared."""
        if any(abs(v) > _TOL for v in self.g92):
            raise ReferenceMismatchError(f"turntable on {port} still has a G92 offset {self.g92} after G92.1")
        if status.wco is not None and any(abs(a - b) > _TOL for a, b in zip(status.wco, self.wco)):
            raise ReferenceMismatchError(f"turntable on {port} reports WCO {status.wco} but its G54 reference "
                                         f"is {self.g54} and G92 {self.g92}")


def read_reference(proto: GrblProtocol, timeout_s: float) -> Reference:
    """Parse `$#` (`[G54:x,y,z]` ... `[G92:x,y,z]`); GRBL refuses it with error:8 while moving."""
    lines = proto.command("$#", timeout_s)
    offsets: dict[str, str] = {}
    for text in lines:
        name, colon, rest = text.strip("[]").partition(":")
        if colon:
            offsets[name] = rest.split(":")[0]
    try:
        g54 = tuple(float(v) for v in offsets["G54"].split(","))
        g92 = tuple(float(v) for v in offsets["G92"].split(","))
    except (KeyError, ValueError) as exc:
        raise DeviceError(f"turntable on {proto.port} sent unreadable $# offsets {lines!r}") from exc
    return Reference(g54, g92)
