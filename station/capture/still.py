"""Adapts a PTP camera to the session's expose-now, download-later interface."""

from __future__ import annotations

from dataclasses import dataclass

from station.capture.ptp import PtpCamera


@dataclass
class PendingPtpObject:
    """A frame the camera has stored; downloading it may overlap the next turntable move."""

    camera: PtpCamera
    handle: int

    def download(self) -> bytes:
        return self.camera.download(self.handle).data


class PtpStillCamera:
    """The session's StillCamera on top of a PtpCamera whose session is open."""

    def __init__(self, camera: PtpCamera):
        self.camera = camera

    def configure(self, exposure_s: float, iso: int) -> None:
        self.camera.set_exposure(exposure_s)
        self.camera.set_iso(iso)

    def trigger(self) -> PendingPtpObject:
        return PendingPtpObject(self.camera, self.camera.trigger())
