"""A camera through libgphoto2 (python-gphoto2): the vendor capture of Canon EOS, Nikon and Sony bodies.

Generic PTP capture (station/capture/ptp.py) is not offered by most system cameras; libgphoto2
speaks their vendor dialects. Settings go through its config widgets, whose names and value
strings differ by vendor (`shutterspeed` "1/30" or "0.0333s", `f-number` "f/8" or "8", `iso`
"100"), so values are parsed, the nearest offered step is chosen, and what the camera reports
back is what the scan records. A widget the body lacks is an error that names it, never a crash.

libgphoto2 reads its camera and I/O library folders once, at import: the module is imported
only when a gphoto2:// camera is opened.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import Any

from station.capture.still import CameraReport, CameraSettings
from station.errors import BadInputError, DeviceDisconnectedError, DeviceError

log = logging.getLogger(__name__)

MAX_STEP_STOPS = 1 / 6  # a setting further than this from what was asked is refused, not rounded
_IO_ERRORS = {-7, -34, -35, -52, -53, -105}  # GP_ERROR_IO*, USB find/claim, model gone: the body went away
_RAW_WORDS = ("raw", "nef", "cr2", "cr3", "arw", "dng", "orf", "raf", "rw2")


def parse_seconds(text: str) -> float | None:
    """Exposure time from a widget string: "1/30", "0.0333s", "2", '2"', "1/30s"; None for bulb or auto."""
    text = text.strip().lower().rstrip("s").replace('"', "").strip()
    fraction = re.fullmatch(r"(\d+(?:\.\d+)?)\s*/\s*(\d+(?:\.\d+)?)", text)
    if fraction:
        return float(fraction.group(1)) / float(fraction.group(2))
    try:
        value = float(text)
    except ValueError:
        return None
    return value if value > 0 else None


def parse_fnumber(text: str) -> float | None:
    match = re.fullmatch(r"f?/?\s*(\d+(?:\.\d+)?)", text.strip().lower())
    return float(match.group(1)) if match else None


def parse_iso(text: str) -> float | None:
    return float(text) if text.strip().isdigit() else None


def nearest_choice(choices: list[str], wanted: float, parse: Any, what: str, camera: str) -> str:
    """The offered choice nearest `wanted` in stops; refused when none lies within MAX_STEP_STOPS."""
    values = [(c, parse(c)) for c in choices]
    usable = [(c, v) for c, v in values if v]
    if not usable:
        raise DeviceError(f"{camera}: the {what} widget offers no numeric value ({', '.join(choices[:8])})")
    best, value = min(usable, key=lambda cv: abs(math.log2(cv[1] / wanted)))
    if abs(math.log2(value / wanted)) > MAX_STEP_STOPS:
        raise BadInputError(f"{camera}: {what} {wanted:g} is not offered (nearest {best!r}); change it in the config")
    return best


class MissingWidgetError(DeviceError):
    """The body has no libgphoto2 config widget of that name (the virtual camera has no `iso`)."""


@dataclass
class PendingGphoto2File:
    """A file the camera has stored; `download` fetches it and deletes it from the card."""

    camera: Gphoto2Camera
    folder: str
    name: str

    def download(self) -> bytes:
        return self.camera.download(self.folder, self.name)


class Gphoto2Camera:
    """One camera libgphoto2 drives; after the body went away (USB unplug, power cycle) the next call opens it again."""

    def __init__(self, port: str | None) -> None:
        import gphoto2

        self.gp = gphoto2
        self.port = port
        self._camera: Any = None
        self.model = ""
        self._settings: CameraSettings | None = None
        self._open()

    @property
    def name(self) -> str:
        return " ".join(p for p in ("gphoto2 camera", self.model, "on", self.port or "any port") if p)

    def _open(self) -> None:
        gp = self.gp
        camera = gp.Camera()
        try:
            if self.port:
                ports = gp.PortInfoList()
                ports.load()
                index = ports.lookup_path(self.port)
                camera.set_port_info(ports[index])
            camera.init()
        except gp.GPhoto2Error as exc:
            found = gp.Camera.autodetect()
            detected = [f"{found.get_name(i)} on {found.get_value(i)}" for i in range(found.count())]
            raise DeviceDisconnectedError(f"no libgphoto2 camera on {self.port or 'any port'} ({exc}); "
                                          f"detected: {', '.join(detected) or 'none'}") from None
        self._camera = camera
        self.model = camera.get_abilities().model
        self.port = camera.get_port_info().get_path()

    def _call(self, what: str, action: Any) -> Any:
        """Run a libgphoto2 call; an I/O error drops the camera, to be reopened by the next capture."""
        if self._camera is None:
            self._reopen()
        try:
            return action(self._camera)
        except self.gp.GPhoto2Error as exc:
            if exc.code in _IO_ERRORS:
                self._drop()
                raise DeviceDisconnectedError(f"{self.name}: gone during {what} ({exc})") from None
            raise DeviceError(f"{self.name}: {what} failed ({exc})") from None

    def _drop(self) -> None:
        camera, self._camera = self._camera, None
        if camera is not None:
            try:
                camera.exit()
            except self.gp.GPhoto2Error:
                log.warning("%s: exit after a lost connection failed", self.name)

    def _reopen(self) -> None:
        log.warning("%s: reconnecting", self.name)
        self._open()
        if self._settings is not None:
            self.apply(self._settings)

    # -- settings ------------------------------------------------------------------------------
    def _widget(self, name: str) -> Any:
        try:
            return self._call(f"reading {name}", lambda cam: cam.get_single_config(name))
        except DeviceDisconnectedError:
            raise
        except DeviceError as exc:
            raise MissingWidgetError(f"{self.name} has no '{name}' setting through libgphoto2 ({exc}); "
                              f"set it on the camera body, or leave it out of the config") from None

    def _choose(self, name: str, wanted: float, parse: Any, what: str) -> float:
        widget = self._widget(name)
        choice = nearest_choice([widget.get_choice(i) for i in range(widget.count_choices())], wanted, parse, what,
                                self.name)
        widget.set_value(choice)
        self._call(f"setting {name}", lambda cam: cam.set_single_config(name, widget))
        readback = parse(self._widget(name).get_value())
        if not readback:
            raise DeviceError(f"{self.name}: {what} reads back as {self._widget(name).get_value()!r} after setting {choice!r}")
        return float(readback)

    def apply(self, settings: CameraSettings) -> CameraSettings:
        """Set shutter speed, ISO and aperture; returns what the camera reports it now uses.

        Exposure time must be settable. A body without an ISO or aperture widget keeps its own
        (set on the body): the value asked for is returned, listed in `unverified`, and logged.
        """
        exposure = self._choose("shutterspeed", settings.exposure_s, parse_seconds, "exposure time (s)")
        iso, aperture, unverified = float(settings.iso), settings.aperture, []
        for name, wanted, parse, what in (("iso", settings.iso, parse_iso, "ISO"),
                                          ("f-number", settings.aperture, parse_fnumber, "aperture")):
            if not wanted:
                continue
            try:
                got = self._choose(name, wanted, parse, what)
            except MissingWidgetError as exc:
                log.warning("%s", exc)
                unverified.append(name)
                continue
            iso, aperture = (got, aperture) if name == "iso" else (iso, got)
        self._settings = CameraSettings(exposure, int(iso), aperture, tuple(unverified))
        return self._settings

    def configure(self, exposure_s: float, iso: int) -> None:
        aperture = self._settings.aperture if self._settings else 0.0
        self.apply(CameraSettings(exposure_s, iso, aperture))

    # -- capture -------------------------------------------------------------------------------
    def trigger(self) -> PendingGphoto2File:
        path = self._call("capture", lambda cam: cam.capture(self.gp.GP_CAPTURE_IMAGE))
        return PendingGphoto2File(self, path.folder, path.name)

    def download(self, folder: str, name: str) -> bytes:
        """The file's bytes, unchanged; deleted from the camera once they are in memory."""
        def fetch(cam: Any) -> bytes:
            camera_file = cam.file_get(folder, name, self.gp.GP_FILE_TYPE_NORMAL)  # owns the buffer: keep it alive
            return bytes(memoryview(camera_file.get_data_and_size()))

        data = self._call(f"download of {folder}/{name}", fetch)
        self._call(f"delete of {folder}/{name}", lambda cam: cam.file_delete(folder, name))
        return data

    # -- health --------------------------------------------------------------------------------
    def value(self, name: str) -> str | None:
        """The current value of a config widget, or None when the body has no such widget."""
        try:
            return str(self._widget(name).get_value())
        except MissingWidgetError:
            return None

    def report(self) -> CameraReport:
        manufacturer = self.value("manufacturer") or ""
        report = CameraReport(model=f"{manufacturer} {self.model}".strip(), battery=self.value("batterylevel"))
        storage = self._call("storage query", lambda cam: cam.get_storageinfo())
        if storage:
            report.storage_free_mb = sum(s.freekbytes for s in storage) / 1024.0
            if report.storage_free_mb <= 0:
                report.problems.append("the camera's storage is full")
        else:
            report.problems.append("the camera reports no storage (no card?)")
        for name in ("imageformat", "imagequality"):
            choice = self.value(name)
            if choice is not None:
                report.raw_formats = (choice,)
                if not any(word in choice.lower() for word in _RAW_WORDS):
                    report.problems.append(f"'{name}' is {choice!r}, not a raw format: set the camera to shoot raw")
                elif "+" in choice:  # raw plus JPEG: one capture would leave the second file on the card
                    report.problems.append(f"'{name}' is {choice!r}: set raw only, without the JPEG")
        return report

    def close(self) -> None:
        self._drop()


def open_gphoto2_camera(port: str | None = None) -> Gphoto2Camera:
    """The camera on libgphoto2 port `port` (e.g. "usb:001,004"), or the first one detected."""
    return Gphoto2Camera(port)
