"""Still cameras as the session and `station rig check` see them, and the PTP camera adapted to that.

Every backend (pyusb PTP, libgphoto2, the simulator's) answers the same questions: which
exposure it really uses once set, what it is and how it is (model, battery, storage, raw), and
expose-now, download-later so a download can overlap the next turntable move.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field

import numpy as np
import rawpy
import tifffile

from station.capture.ptp import PtpCamera
from station.capture.ptp_codec import DevicePropCode, ObjectFormat, OperationCode
from station.errors import DeviceError

log = logging.getLogger(__name__)

PTP_FNUMBER = 0x5007  # u16, f-number x 100 (ISO 15740 FNumber)
RAW_FORMATS = {ObjectFormat.DNG: "dng", ObjectFormat.TIFF: "tiff"}


@dataclass(frozen=True)
class CameraSettings:
    """Exposure for every frame of a scan; `aperture` 0 means the lens is left as it is."""

    exposure_s: float
    iso: int
    aperture: float = 0.0
    unverified: tuple[str, ...] = ()  # settings the body keeps itself (no control for them): as asked, not read back


@dataclass
class CameraReport:
    """What `station rig check` tells the operator about a camera; None: the camera does not say."""

    model: str
    battery: str | None = None
    storage_free_mb: float | None = None
    raw_formats: tuple[str, ...] = ()
    problems: list[str] = field(default_factory=list)  # each one fails the check


@dataclass(frozen=True)
class RawInfo:
    """What LibRaw reads from a raw file: its colour filter layout and size."""

    cfa: str  # e.g. "RGGB", read from the file, never assumed
    width: int
    height: int
    format: str  # dng, nef, cr2, arw, cr3, raf, orf, rw2, or tiff for another TIFF-based raw


_TIFF_MAKERS = {"nikon": "nef", "canon": "cr2", "sony": "arw", "olympus": "orf", "panasonic": "rw2"}


def raw_format(data: bytes) -> str:
    """The raw container, from its magic bytes and, for TIFF-based raws, the DNGVersion or Make tag."""
    if data[4:11] == b"ftypcrx":
        return "cr3"
    if data.startswith(b"FUJIFILM"):
        return "raf"
    if data[:4] in (b"IIRO", b"IIRS", b"MMOR"):
        return "orf"
    if data[:4] == b"IIU\x00":
        return "rw2"
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            tags = tif.pages[0].tags
            if 50706 in tags:
                return "dng"
            make = str(tags[271].value).lower() if 271 in tags else ""
    except (tifffile.TiffFileError, ValueError, IndexError):
        return "unknown"
    return next((ext for maker, ext in _TIFF_MAKERS.items() if maker in make), "tiff")


def inspect_raw(data: bytes, source: str) -> RawInfo:
    """Open `data` as a raw with LibRaw; a JPEG or a raw without a 2x2 Bayer pattern is refused."""
    try:
        with rawpy.imread(io.BytesIO(data)) as raw:
            pattern = np.asarray(raw.raw_pattern)
            desc = raw.color_desc.decode("ascii")
            height, width = raw.raw_image_visible.shape
    except (rawpy.LibRawError, ValueError) as exc:
        kind = "a JPEG" if data[:2] == b"\xff\xd8" else "not a raw LibRaw reads"
        raise DeviceError(f"{source}: the camera delivered {kind} ({exc}); set it to shoot raw") from None
    if pattern is None or pattern.shape != (2, 2) or pattern.max() >= len(desc):
        raise DeviceError(f"{source}: the raw has no 2x2 Bayer pattern (LibRaw pattern {pattern!r})")
    return RawInfo("".join(desc[i] for i in pattern.flatten()), int(width), int(height), raw_format(data))


@dataclass
class PendingPtpObject:
    """A frame the camera has stored; downloading it may overlap the next turntable move."""

    camera: PtpCamera
    handle: int

    def download(self) -> bytes:
        return self.camera.download(self.handle).data


class PtpStillCamera:
    """The station's camera on top of a PtpCamera whose session is open."""

    def __init__(self, camera: PtpCamera):
        self.camera = camera

    def _supports(self, prop: int) -> bool:
        info = self.camera.device_info
        return bool(info and prop in info.device_properties_supported)

    def apply(self, settings: CameraSettings) -> CameraSettings:
        """Set exposure, ISO and aperture (all or none); returns what the camera will really use."""
        if settings.aperture and not self._supports(PTP_FNUMBER):
            raise DeviceError(f"{self.camera.transport.description} has no FNumber property (0x5007); "
                              "set the aperture on the lens and put aperture = 0 in the config")
        exposure = self.camera.set_exposure(settings.exposure_s)
        iso = self.camera.set_iso(settings.iso)
        aperture = 0.0
        if settings.aperture:
            self.camera.set_prop_value(PTP_FNUMBER, round(settings.aperture * 100))
            aperture = int(self.camera.get_prop_value(PTP_FNUMBER)) / 100  # type: ignore[arg-type]
        return CameraSettings(exposure, iso, aperture)

    def configure(self, exposure_s: float, iso: int) -> None:
        self.camera.set_exposure(exposure_s)
        self.camera.set_iso(iso)

    def trigger(self) -> PendingPtpObject:
        return PendingPtpObject(self.camera, self.camera.trigger())

    def report(self) -> CameraReport:
        info = self.camera.describe()
        device = self.camera.device_info
        formats = tuple(RAW_FORMATS[f] for f in (device.capture_formats if device else ()) if f in RAW_FORMATS)
        report = CameraReport(model=f"{info['manufacturer']} {info['model']}".strip(), raw_formats=formats)
        if self._supports(DevicePropCode.BatteryLevel):
            report.battery = f"{self.camera.get_prop_value(DevicePropCode.BatteryLevel)} %"
        if device and OperationCode.GetStorageIDs not in device.operations_supported:
            report.problems.append("the camera lists no storage (GetStorageIDs unsupported)")
        if not formats:
            report.problems.append("the camera offers no raw capture format (DNG or TIFF) over PTP")
        return report

    def close(self) -> None:
        self.camera.close()

