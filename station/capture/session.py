"""The scan session: runs a ScanPlan against a turntable and a camera, and owns the manifest.

Devices only speak their protocols; the plan is data; this engine decides what still needs
shooting (resume), retries after device recovery, overlaps motion with downloads, and makes
sure nothing captured is ever lost: each raw is written atomically first, then the manifest is
rewritten atomically. A kill between the two leaves an unlisted raw that the next run re-shoots,
never a listed frame without its file.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable, Literal, Protocol

from station import __version__
from station.capture.plan import PlannedFrame, ScanPlan
from station.errors import DeviceError, ScanFolderError, StationError
from station.rig_geometry import RigGeometry
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_bytes, atomic_write_json, require_free_space, sha256_bytes

log = logging.getLogger(__name__)


class MoveStatus(Protocol):
    def wait(self, timeout: float | None = None) -> object: ...


class RecoveryOutcome(Protocol):
    exact: bool  # False: the board lost its step count mid-move and was not re-homed


class TurntableAxes(Protocol):
    """What the session needs from a turntable driver (station.turntable.grbl.Turntable)."""

    position_exact: bool  # False once a reset or reboot left the position a best guess

    def move_to(self, angle_deg: float, tilt_deg: float) -> MoveStatus: ...

    def recover(self) -> RecoveryOutcome: ...


class PendingFrame(Protocol):
    """An exposure that has completed on the camera but not yet been downloaded."""

    def download(self) -> bytes: ...


class StillCamera(Protocol):
    """What the session needs from a camera: expose now, download later (so motion can overlap)."""

    def configure(self, exposure_s: float, iso: int) -> None: ...

    def trigger(self) -> PendingFrame: ...


OperatorAction = Literal["clear_turntable", "place_stone"]


class Operator(Protocol):
    """Whoever places and removes the stone: a person at a prompt, or the simulator.

    `request` returns once the action is done (a person confirms at the prompt).
    """

    def request(self, action: OperatorAction, message: str) -> None: ...


class ScanCancelledError(StationError):
    """The operator cancelled the scan between frames; every frame shot so far is kept for a resume."""

    exit_code = 2


class ScanControl:
    """Pause, resume and cancel from another thread (a dashboard), honoured between frames.

    The session calls `checkpoint` before each exposure, once the turntable has confirmed it
    stands at that frame's pose: a pause holds the rig still there, and a cancel stops the scan
    with every frame so far in the manifest, so running the session again resumes it.
    """

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._paused = False
        self._cancelled = False
        self.current: PlannedFrame | None = None  # the frame the rig stands ready to shoot
        self.holding = False  # True while a pause is in effect: the session waits, the rig is at rest

    @property
    def paused(self) -> bool:
        """A pause was asked for; it takes effect at the next frame boundary (see `holding`)."""
        return self._paused

    def pause(self) -> None:
        with self._changed:
            self._paused = True

    def resume(self) -> None:
        with self._changed:
            self._paused = self.holding = False
            self._changed.notify_all()

    def cancel(self) -> None:
        with self._changed:
            self._cancelled = True
            self._changed.notify_all()

    def checkpoint(self, frame: PlannedFrame) -> None:
        """Block while paused (as long as the operator wants); raise ScanCancelledError once cancelled."""
        with self._changed:
            self.current = frame
            while self._paused and not self._cancelled:
                self.holding = True
                self._changed.wait()
            self.holding = False
            if self._cancelled:
                raise ScanCancelledError(f"scan cancelled by the operator before {frame.file}; run it again to resume")


@dataclass
class SessionConfig:
    move_timeout_s: float = 120.0
    device_retries: int = 2  # recoveries tried per frame before the fault goes to the operator
    overlap_motion: bool = True  # move to the next pose while this frame downloads (off only to measure the gain)
    bytes_per_frame_hint: int = 0  # 0: estimate from the rig's resolution


@dataclass
class ScanSummary:
    shot: list[str] = field(default_factory=list)
    reshot_corrupt: list[str] = field(default_factory=list)
    skipped_verified: list[str] = field(default_factory=list)
    recoveries: int = 0

    @property
    def total(self) -> int:
        return len(self.shot) + len(self.skipped_verified)


def _utc_now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


class ScanSession:
    """Runs one plan into one scan folder; safe to run again on the same folder to resume."""

    def __init__(
        self,
        scan: ScanFolder,
        plan: ScanPlan,
        rig: RigGeometry,
        turntable: TurntableAxes,
        camera: StillCamera,
        operator: Operator,
        stone_id: str,
        config: SessionConfig | None = None,
        progress: Callable[[int, int, str], None] | None = None,
        control: ScanControl | None = None,
    ):
        self.scan, self.plan, self.rig = scan, plan, rig
        self.turntable, self.camera, self.operator = turntable, camera, operator
        self.stone_id = stone_id
        self.config = config or SessionConfig()
        self.progress = progress or (lambda done, total, what: None)
        self.control = control or ScanControl()
        self._plan_order = {frame.file: i for i, frame in enumerate(plan.frames())}  # the manifest's line order

    # ------------------------------------------------------------------------------------
    def run(self) -> ScanSummary:
        self._check_or_write_scan_json()
        summary = ScanSummary()
        entries = self._verified_entries(summary)
        todo = [frame for frame in self.plan.frames() if frame.file not in entries]
        self._check_disk(len(todo))
        self._drop_unlisted_raws(entries)
        total = len(self.plan.frames())
        self.progress(total - len(todo), total, "resuming" if entries else "starting")

        self.camera.configure(self.plan.exposure_s, self.plan.iso)
        plates = [f for f in todo if f.kind == "plate"]
        shots = [f for f in todo if f.kind == "shot"]
        if plates:
            self.operator.request("clear_turntable", "Remove the stone: empty background plates are shot first.")
            self._shoot_all(plates, entries, summary, total)
        if shots:
            self.operator.request("place_stone", "Place the stone on the centre of the turntable.")
            self._shoot_all(shots, entries, summary, total)
        self.scan.mark_done("capture", {"frames": total, "software": __version__, "utc": _utc_now()})
        return summary

    # ------------------------------------------------------------------------------------
    def _shoot_all(self, frames: list[PlannedFrame], entries: dict[str, ManifestEntry], summary: ScanSummary, total: int) -> None:
        """Shoot frames in order; while frame k downloads and is written, the rig moves to k+1."""
        self._move(frames[0], summary)
        for k, frame in enumerate(frames):
            self.control.checkpoint(frame)
            pending = self._trigger(frame, summary)
            following = frames[k + 1] if k + 1 < len(frames) else None
            overlap = following is not None and self.config.overlap_motion
            move = self._start_move(following, summary) if overlap else None
            data = pending.download()
            self._store(frame, data, entries)
            if following is not None and not overlap:
                move = self._start_move(following, summary)
            summary.shot.append(frame.file)
            self.progress(len(entries), total, frame.file)
            if following is not None:
                self._finish_move(move, following, summary)

    def _trigger(self, frame: PlannedFrame, summary: ScanSummary) -> PendingFrame:
        for attempt in range(self.config.device_retries + 1):
            try:
                return self.camera.trigger()
            except DeviceError as exc:
                if attempt == self.config.device_retries:
                    raise DeviceError(f"camera failed on {frame.file} after {attempt + 1} attempts: {exc}") from exc
                log.warning("camera fault on %s (%s); retrying", frame.file, exc)
                summary.recoveries += 1
        raise AssertionError("unreachable")

    def _start_move(self, frame: PlannedFrame, summary: ScanSummary) -> MoveStatus | None:
        try:
            return self.turntable.move_to(frame.azimuth_deg, frame.elevation_deg)
        except (DeviceError, TimeoutError) as exc:
            log.warning("turntable fault starting move to %s (%s); will recover", frame.file, exc)
            return None

    def _finish_move(self, move: MoveStatus | None, frame: PlannedFrame, summary: ScanSummary) -> None:
        if move is not None:
            try:
                move.wait(self.config.move_timeout_s)
                return
            except (DeviceError, TimeoutError) as exc:
                log.warning("turntable fault moving to %s (%s); recovering", frame.file, exc)
        self._recover(frame, summary)
        self._move(frame, summary)

    def _move(self, frame: PlannedFrame, summary: ScanSummary) -> None:
        """Blocking move with recovery: reconnect, re-establish position, then try again."""
        for attempt in range(self.config.device_retries + 1):
            try:
                self.turntable.move_to(frame.azimuth_deg, frame.elevation_deg).wait(self.config.move_timeout_s)
                return
            except (DeviceError, TimeoutError) as exc:
                if attempt == self.config.device_retries:
                    raise DeviceError(
                        f"turntable could not reach elevation {frame.elevation_deg} deg, azimuth "
                        f"{frame.azimuth_deg} deg for {frame.file} after {attempt + 1} attempts: {exc}"
                    ) from exc
                log.warning("turntable fault (%s); recovering before %s", exc, frame.file)
                self._recover(frame, summary)

    def _recover(self, frame: PlannedFrame, summary: ScanSummary) -> None:
        summary.recoveries += 1
        if not self.turntable.recover().exact:
            log.warning(
                "turntable lost its position without homing; angles from %s on may be off and are marked "
                "pose_exact=false in the manifest. Enable homing ($22=1) for exact recovery.", frame.file,
            )

    def _store(self, frame: PlannedFrame, data: bytes, entries: dict[str, ManifestEntry]) -> None:
        path = self.scan.resolve_inside(frame.file)
        atomic_write_bytes(path, data)
        entries[frame.file] = ManifestEntry(
            file=frame.file,
            sha256=sha256_bytes(data),
            elevation_deg=frame.elevation_deg,
            azimuth_deg=frame.azimuth_deg,
            kind=frame.kind,
            exposure_s=self.plan.exposure_s,
            iso=self.plan.iso,
            utc=_utc_now(),
            extra={"elevation_index": frame.elevation_index}
            | ({} if self.turntable.position_exact else {"pose_exact": False}),
        )
        order = self._plan_order
        self.scan.write_manifest(sorted(entries.values(), key=lambda e: order.get(e.file, len(order))))

    # ------------------------------------------------------------------------------------
    def _check_or_write_scan_json(self) -> None:
        record = {
            "stone_id": self.stone_id,
            "plan": self.plan.to_dict(),
            "rig": self.rig.to_dict(),
            "camera": {"exposure_s": self.plan.exposure_s, "iso": self.plan.iso},
            "software": {"station": __version__},
        }
        if self.scan.scan_json.exists():
            existing = self.scan.read_scan_json()
            if existing.get("plan") != record["plan"] or existing.get("stone_id") != record["stone_id"]:
                raise ScanFolderError(
                    f"{self.scan.scan_json}: this folder holds a different scan (stone "
                    f"{existing.get('stone_id')!r}, plan {existing.get('plan')}); use a new --out folder"
                )
            return
        record["started_utc"] = _utc_now()
        atomic_write_json(self.scan.scan_json, record)

    def _verified_entries(self, summary: ScanSummary) -> dict[str, ManifestEntry]:
        planned = {f.file for f in self.plan.frames()}
        entries: dict[str, ManifestEntry] = {}
        for entry in self.scan.read_manifest():
            if entry.file not in planned:
                continue
            if self.scan.verify_entry(entry):
                entries[entry.file] = entry
                summary.skipped_verified.append(entry.file)
            else:
                log.warning("%s: missing or checksum mismatch; re-shooting", entry.file)
                summary.reshot_corrupt.append(entry.file)
        return entries

    def _drop_unlisted_raws(self, entries: dict[str, ManifestEntry]) -> None:
        """A raw without a manifest line was written by a run killed before it was listed: re-shoot it."""
        if not self.scan.raw_dir.exists():
            return
        for path in self.scan.raw_dir.iterdir():
            relative = f"raw/{path.name}"
            if relative not in entries:
                path.unlink()

    def _check_disk(self, frames_left: int) -> None:
        per_frame = self.config.bytes_per_frame_hint or (self.rig.width * self.rig.height * 2 + 64 * 1024)
        require_free_space(self.scan.root, int(frames_left * per_frame * 1.5) + (16 << 20), f"scan into {self.scan.root}")
