"""A whole simulated rig, built on demand: emulated GRBL board, simulated PTP camera, stone world.

The real drivers talk to it through their real code paths (pyserial on a `fakegrbl://` URL or a
pty; pyusb through a pure-Python backend), so a scan on this rig exercises the same code as a
scan on hardware. The camera renders the view at the emulated turntable's physical position at
the moment of exposure. The simulated operator takes the stone off for the plates and puts it
back. After a scan, `write_truth` records what really was in front of the camera, the truth image
of each shot kept from its exposure (staged in a temporary folder until the scan's file names are known).
"""

from __future__ import annotations

import tempfile
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from sim.dng import dng_bytes
from sim.grbl_links import FakeTurntable, start_fake_turntable
from sim.lens import SimLens
from sim.ptp_camera import CaptureSettings, SimPtpCamera
from sim.scene import World, frame_source, render
from sim.sensor import SensorModel
from sim.stone import Stone, load_stone_mesh, procedural_stone
from sim.truth import (TruthFrame, TruthImage, add_truth_image_file, image_path_for, write_truth_frames,
                       write_truth_image)
from sim.usb_backend import SimUsbBackend
from station.capture.ptp import PtpCamera, open_ptp_camera
from station.capture.still import PtpStillCamera
from station.rig_geometry import RigGeometry
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_bytes, atomic_write_json, sha256_bytes
from station.turntable.grbl import Turntable, TurntableConfig


def make_stone(spec: str | None, seed: int = 0) -> Stone:
    """`spec` is a mesh path, a seed ("7"), or "look:seed" (e.g. "pale:3"); None gives the default stone."""
    if spec is None:
        return procedural_stone(seed)
    if Path(spec).suffix.lower() in (".ply", ".obj", ".stl", ".glb", ".off"):
        return load_stone_mesh(Path(spec), seed=seed)
    look, _, number = spec.rpartition(":")
    return procedural_stone(int(number), look=look or "grey")  # type: ignore[arg-type]


Shot = tuple[float, float, np.ndarray, Path]  # (elevation_deg, azimuth_deg, true mask, staged truth image)


class SimOperator:
    """Does what the session asks, instantly: lifts the stone off for plates, puts it back for shots."""

    def __init__(self, world: World):
        self.world = world
        self.requests: list[str] = []

    def request(self, action: Literal["clear_turntable", "place_stone"], message: str) -> None:
        self.requests.append(action)
        self.world.stone_present = action == "place_stone"


@dataclass
class SimRig:
    world: World
    board: FakeTurntable
    camera_device: SimPtpCamera
    turntable: Turntable
    ptp: PtpCamera
    operator: SimOperator
    staging: tempfile.TemporaryDirectory
    truth_writer: ThreadPoolExecutor  # stages each shot's truth image while the scan goes on
    shots: list[Shot] = field(default_factory=list)  # as exposed
    staged: list[Future] = field(default_factory=list)  # the truth images being written

    @property
    def camera(self) -> PtpStillCamera:
        return PtpStillCamera(self.ptp)

    def write_truth(self, scan: ScanFolder) -> None:
        """sim_truth/ for every frame in the manifest, at the pose the stage physically had.

        The board's step quantisation leaves the stage a few hundredths of a degree off the plan,
        and the truth must say where the camera really was; masks rendered at exposure are reused.
        Frames shot by an earlier (killed) run were not seen by this rig and are rendered anew.
        """
        for write in self.staged:
            write.result()  # a failed write is raised here
        frames, staged_images = [], []
        for entry in scan.read_manifest():
            elevation, azimuth, mask = entry.elevation_deg, entry.azimuth_deg, None
            if entry.kind == "plate":
                mask = np.zeros((self.world.rig.height, self.world.rig.width), dtype=bool)
            else:
                exposed = _nearest_shot(self.shots, entry.elevation_deg, entry.azimuth_deg)
                if exposed is not None:
                    elevation, azimuth, mask, staged = exposed
                    staged_images.append((entry.file, staged))
                else:  # written now: a resumed scan may have many, and each image is megabytes
                    out = render(self.world, elevation, azimuth, stone_present=True, supersample=2)
                    mask = out.mask
                    write_truth_image(image_path_for(scan.root, entry.file), TruthImage.of(out))
            frames.append(TruthFrame(entry.file, elevation, azimuth, mask))
        write_truth_frames(scan.root, self.world, frames)
        for file, staged in staged_images:
            add_truth_image_file(scan.root, file, staged)

    def close(self) -> None:
        self.ptp.close()
        self.turntable.close()
        self.board.close()
        self.truth_writer.shutdown(wait=True)
        self.staging.cleanup()

    def __enter__(self) -> "SimRig":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _nearest_shot(shots: list[Shot], elevation_deg: float, azimuth_deg: float, tolerance_deg: float = 0.5) -> Shot | None:
    """The exposure taken closest to a planned pose (latest wins, as a re-shot replaces a frame)."""
    best, best_error = None, tolerance_deg
    for shot in shots:
        turn_error = abs((shot[1] - azimuth_deg + 180.0) % 360.0 - 180.0)
        error = max(abs(shot[0] - elevation_deg), turn_error)
        if error <= best_error:
            best, best_error = shot, error
    return best


def build_sim_rig(
    stone: Stone,
    rig: RigGeometry = RigGeometry(),
    *,
    time_scale: float = 0.05,
    route: Literal["url", "pty"] = "url",
    seed: int = 0,
    lens: SimLens = SimLens(),
) -> SimRig:
    """Start the emulators, connect the real drivers to them, and return the assembled rig."""
    world = World(stone, rig=rig, lens=lens)
    sensor = SensorModel(lens=lens)
    board = start_fake_turntable(route, time_scale=time_scale, seed=seed)
    render = frame_source(world, board.firmware.position, sensor, seed)
    staging = tempfile.TemporaryDirectory(prefix="sim-truth-")
    # one thread: the EXR encoder lets go of the GIL, so the next shot renders while this one's truth is written
    truth_writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-truth")
    shots: list[Shot] = []
    staged_writes: list[Future] = []

    def shoot(settings: CaptureSettings) -> tuple[bytes, str]:
        data, name = render(settings)
        if world.stone_present:
            elevation, azimuth = render.last_pose
            staged = Path(staging.name) / f"{render.count:05d}.exr"
            staged_writes.append(truth_writer.submit(write_truth_image, staged, TruthImage.of(render.last)))
            shots.append((elevation, azimuth, render.last.mask, staged))
        return data, name

    camera_device = SimPtpCamera(shoot, time_scale=time_scale)
    try:
        turntable = Turntable.connect(board.port, TurntableConfig())
    except BaseException:
        board.close()
        truth_writer.shutdown()
        staging.cleanup()
        raise
    ptp = open_ptp_camera(backend=SimUsbBackend(camera_device))
    return SimRig(world, board, camera_device, turntable, ptp, SimOperator(world), staging, truth_writer, shots,
                  staged_writes)


def direct_scan(
    root: Path, stone: Stone, rig: RigGeometry, elevations: tuple[float, ...], azimuths: int,
    *, exposure_s: float = 1 / 30, seed: int = 0, lens: SimLens = SimLens(),
) -> ScanFolder:
    """A scan as capture leaves it (raw DNGs with one plate per ring, manifest, scan.json, sim_truth/), rendered
    straight at the planned poses without the emulated board and camera: quick, for benches and tests."""
    world, sensor, scan = World(stone, rig, lens=lens), SensorModel(lens=lens), ScanFolder(root)
    entries, frames = [], []
    for i, elevation in enumerate(elevations):
        for j in [None, *range(azimuths)]:
            azimuth = 0.0 if j is None else 360.0 * j / azimuths
            name = f"raw/{f'plate_e{i}' if j is None else f'e{i}_a{j:03d}'}.dng"
            out = render(world, elevation, azimuth, stone_present=j is not None)
            rng = np.random.default_rng([seed, i, azimuths if j is None else j])
            data = dng_bytes(sensor.expose(out.radiance, exposure_s, 100, rng), sensor)
            atomic_write_bytes(scan.root / name, data)
            kind = "plate" if j is None else "shot"
            entries.append(ManifestEntry(name, sha256_bytes(data), elevation, azimuth, kind, exposure_s, 100, ""))
            if j is not None:
                write_truth_image(image_path_for(scan.root, name), TruthImage.of(out))
            frames.append(TruthFrame(name, elevation, azimuth, out.mask))
    write_truth_frames(scan.root, world, frames)
    scan.write_manifest(entries)
    atomic_write_json(scan.scan_json, {"rig": rig.to_dict(), "plan": {"elevations_deg": list(elevations),
                                                                      "azimuths": azimuths}})
    return scan
