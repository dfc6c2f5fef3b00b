"""Rig assembly by URL: the one place that turns a turntable or camera URL into an open device.

Turntables: `grbl:///dev/ttyUSB0`, a bare device path, or any pyserial URL (`socket://`,
`rfc2217://`, a registered `fakegrbl://NAME`). Cameras: `ptp://usb` (optionally
`ptp://usb?vendor=04a9&product=3294`), `gphoto2://` (the first camera libgphoto2 detects) or
`gphoto2://usb:001,004` (one port). Other schemes (`sim://`, a bare `fakegrbl://`) are opened by
whoever registered them: the simulator's wiring registers its own, so this module, like the rest
of `station/`, never imports `sim/`.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Callable, Protocol
from urllib.parse import parse_qs, urlsplit

from station.capture.session import PendingFrame
from station.capture.still import CameraReport, CameraSettings, PtpStillCamera
from station.errors import BadInputError
from station.rig_geometry import RigGeometry
from station.turntable.grbl import Turntable, TurntableConfig


class RigCamera(Protocol):
    """A camera as the station drives it: settings, expose-now download-later, and a health report."""

    def apply(self, settings: CameraSettings) -> CameraSettings: ...

    def configure(self, exposure_s: float, iso: int) -> None: ...

    def trigger(self) -> PendingFrame: ...

    def report(self) -> CameraReport: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class CameraContext:
    """What a camera opener may need beyond its URL: a simulated camera renders this rig at the table's pose."""

    rig: RigGeometry
    turntable: Turntable | None
    stack: ExitStack  # the opener registers whatever it started, to be closed with the rig


TurntableOpener = Callable[[str, TurntableConfig, ExitStack], Turntable]
CameraOpener = Callable[[str, CameraContext], RigCamera]


def _open_grbl(url: str, config: TurntableConfig, stack: ExitStack) -> Turntable:
    path = urlsplit(url).path
    if not path:
        raise BadInputError(f"turntable URL {url!r}: expected grbl:///dev/ttyUSB0 (a serial device path)")
    return Turntable.connect(path, config)


def _open_ptp(url: str, context: CameraContext) -> RigCamera:
    from station.capture.ptp import open_ptp_camera

    parts = urlsplit(url)
    if parts.netloc not in ("", "usb"):
        raise BadInputError(f"camera URL {url!r}: only ptp://usb is supported (PTP over USB)")
    query = parse_qs(parts.query)
    try:
        ids = {k: int(query[k][0], 16) for k in ("vendor", "product") if k in query}
    except ValueError:
        raise BadInputError(f"camera URL {url!r}: vendor and product are hexadecimal USB ids, e.g. vendor=04a9") from None
    unknown = set(query) - {"vendor", "product"}
    if unknown:
        raise BadInputError(f"camera URL {url!r}: unknown parameter(s) {', '.join(sorted(unknown))}")
    return PtpStillCamera(open_ptp_camera(**ids))


def _open_gphoto2(url: str, context: CameraContext) -> RigCamera:
    from station.capture.gphoto2_camera import open_gphoto2_camera

    return open_gphoto2_camera(url[len("gphoto2://"):] or None)


_TURNTABLES: dict[str, TurntableOpener] = {"grbl": _open_grbl}
_CAMERAS: dict[str, CameraOpener] = {"ptp": _open_ptp, "gphoto2": _open_gphoto2}


def register_turntable_scheme(scheme: str, opener: TurntableOpener) -> None:
    """Let `open_turntable` hand `scheme://...` URLs to `opener` (the simulator's wiring uses this)."""
    _TURNTABLES[scheme] = opener


def register_camera_scheme(scheme: str, opener: CameraOpener) -> None:
    _CAMERAS[scheme] = opener


def _scheme(url: str) -> str:
    return url.split("://", 1)[0].lower() if "://" in url else ""


def open_turntable(url: str, config: TurntableConfig, stack: ExitStack) -> Turntable:
    """Connect to the turntable at `url`; it is closed with `stack`."""
    if not url:
        raise BadInputError("no turntable: give --port or turntable.port in the config, e.g. grbl:///dev/ttyUSB0")
    opener = _TURNTABLES.get(_scheme(url))
    table = opener(url, config, stack) if opener else Turntable.connect(url, config)  # a path or a pyserial URL
    stack.callback(table.close)
    return table


def open_camera(url: str, context: CameraContext) -> RigCamera:
    """Open the camera at `url`; it is closed with `context.stack`."""
    opener = _CAMERAS.get(_scheme(url))
    if opener is None:
        known = ", ".join(f"{s}://" for s in sorted(_CAMERAS))
        raise BadInputError(f"camera URL {url!r}: unknown scheme; expected one of {known}")
    camera = opener(url, context)
    context.stack.callback(camera.close)
    return camera


@dataclass
class Rig:
    """An open turntable and camera, closed together (camera first, as it was opened last)."""

    turntable: Turntable
    camera: RigCamera
    geometry: RigGeometry
    stack: ExitStack = field(repr=False)

    def close(self) -> None:
        self.stack.close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_rig(turntable_url: str, turntable_config: TurntableConfig, camera_url: str, geometry: RigGeometry) -> Rig:
    """Turntable first (a simulated camera renders at its pose), then the camera; nothing stays open on failure."""
    stack = ExitStack()
    try:
        table = open_turntable(turntable_url, turntable_config, stack)
        camera = open_camera(camera_url, CameraContext(geometry, table, stack))
    except BaseException:
        stack.close()
        raise
    return Rig(table, camera, geometry, stack)
