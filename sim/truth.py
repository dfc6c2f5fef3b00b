"""sim_truth/: what a simulated scan really was, for tests and benchmarks to score the pipeline against.

Layout (contract.md): mesh.ply (the true stone, turntable frame, metres), cameras.json (per frame:
file, 4x4 camera-to-world in OpenCV convention, K, the lens's distortion k1, k2, p1, p2, width,
height), masks/<stem>.png (8-bit, 255 = stone) and images/<stem>.exr, the noise-free image an ideal
develop makes of the shot (`TruthImage`);
images_<W>w/ holds it at a training width W, made on first use by `true_images_at`. Frames are added
by `write_truth_frames` (or one at a time) so a scan that resumes after a crash adds its new frames without
rewriting the ones it already has; every write is atomic.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import OpenEXR
from PIL import Image

from sim.lens import SimLens
from sim.scene import RenderOut, World, render
from sim.stone import Stone
from station.errors import BadInputError, ScanFolderError
from station.rig_geometry import RigGeometry, camera_to_turntable
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with

Frame = tuple[str, float, float]  # (file relative to the scan root, elevation_deg, azimuth_deg)


def _truth_paths(scan_root: Path) -> tuple[Path, Path, Path]:
    truth = ScanFolder(scan_root).sim_truth_dir
    return truth / "mesh.ply", truth / "cameras.json", truth / "masks"


def mask_path_for(scan_root: Path, file: str) -> Path:
    """Where the true mask of frame `file` lives: sim_truth/masks/<stem>.png."""
    return _truth_paths(scan_root)[2] / f"{Path(file).stem}.png"


@dataclass
class TruthImage:
    """What an ideal develop makes of a shot: the scene radiance each pixel sees through the lens, in linear
    sRGB primaries, in the sensor's own (distorted) geometry, with the lens's vignetting and the shot's
    exposure error taken out; and the same split into the stone alone. Undistortion is posing's job, after
    the develop, so the develop's output is scored in the sensor's geometry."""

    exposed: np.ndarray  # [H, W, 3] float32: scene radiance, flat-fielded, at the nominal exposure
    stone: np.ndarray  # [H, W, 3] float32: the stone's share of `exposed`, premultiplied by its coverage
    alpha: np.ndarray  # [H, W] float32: the stone's coverage

    @classmethod
    def of(cls, out: RenderOut) -> "TruthImage":
        return cls(exposed=out.radiance, stone=out.stone, alpha=out.alpha)

    def downscaled(self, width: int) -> "TruthImage":
        """Area-averaged to `width` pixels wide: exact, as a render is itself a box filter over its samples."""
        h, w = self.alpha.shape
        if width >= w:
            return self
        size = (width, max(1, round(h * width / w)))
        area = [cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (self.exposed, self.stone, self.alpha)]
        return TruthImage(*area)


def write_truth_image(path: Path, image: TruthImage) -> None:
    """One half-float EXR: R, G, B the exposed image, A the coverage, stone.R/G/B the stone alone."""
    channels = {"RGB": image.exposed, "A": image.alpha, **{f"stone.{c}": image.stone[..., i] for i, c in enumerate("RGB")}}
    channels = {name: np.ascontiguousarray(x.astype(np.float16)) for name, x in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def writer(tmp: Path) -> None:
        with OpenEXR.File(header, channels) as out:
            out.write(str(tmp))

    atomic_write_with(path, writer)


def read_truth_image(path: Path) -> TruthImage:
    try:
        with OpenEXR.File(str(path)) as exr:
            channels = exr.channels()
            rgba, stone = (np.array(channels[name].pixels, dtype=np.float32) for name in ("RGBA", "stone"))
        return TruthImage(exposed=rgba[..., :3], stone=stone, alpha=rgba[..., 3])
    except (OSError, RuntimeError, KeyError, IndexError) as exc:
        raise BadInputError(f"{path}: not a sim_truth image ({exc})") from exc


def image_path_for(scan_root: Path, file: str, width: int | None = None) -> Path:
    """sim_truth/images/<stem>.exr at the sensor's size, or images_<width>w/<stem>.exr at a training width."""
    folder = "images" if width is None else f"images_{width}w"
    return ScanFolder(scan_root).sim_truth_dir / folder / f"{Path(file).stem}.exr"


def add_truth_image_file(scan_root: Path, file: str, staged: Path) -> None:
    """Copy a truth image written at exposure (`SimRig` stages them) to sim_truth/images/."""
    atomic_write_with(image_path_for(scan_root, file), lambda tmp: shutil.copyfile(staged, tmp))


def true_images_at(scan_root: Path, width: int, files: Sequence[str]) -> dict[str, TruthImage]:
    """The truth images of `files` at `width` pixels wide (a scan's training size), averaged down from the
    sensor's and kept in sim_truth/images_<width>w/ beside it."""
    out = {}
    for file in files:
        path = image_path_for(scan_root, file, width)
        ScanFolder(scan_root).resolve_inside(file)
        if path.is_file():
            out[file] = read_truth_image(path)
            continue
        source = image_path_for(scan_root, file)
        if not source.is_file():
            raise ScanFolderError(f"{source}: no truth image for {file} (a scan simulated before they were kept?)")
        full = read_truth_image(source)
        out[file] = full.downscaled(width)
        if out[file] is not full:
            write_truth_image(path, out[file])
    return out


def true_masks_at(scan_root: Path, stone: Stone, width: int, files: Sequence[str]) -> dict[str, np.ndarray]:
    """The true masks [H, W] bool of `files` at `width` pixels wide (a scan's training size), rendered with 16
    samples a pixel where cameras.json says the rig really was (its steps, not the plan): masks/ holds them
    only at the sensor's size, and a 0/1 mask cannot be averaged down."""
    scan_root = Path(scan_root)
    sensor = RigGeometry.from_dict(ScanFolder(scan_root).read_scan_json()["rig"])
    where = {c["file"]: c for c in _read_cameras(_truth_paths(scan_root)[1])}
    lens = _lens_of(where[files[0]]) if files else SimLens()
    world = World(stone, rig=sensor.scaled(width, round(sensor.height * width / sensor.width)), lens=lens)
    return {file: render(world, where[file]["elevation_deg"], where[file]["azimuth_deg"], stone_present=True,
                         supersample=4).mask for file in files}


def _lens_of(record: dict) -> SimLens:
    """The lens a truth camera record was shot through (vignetting and jitter do not change masks)."""
    terms = record.get("distortion", {})
    return SimLens(distortion=any(terms.values()), **terms) if isinstance(terms, dict) else SimLens()


def _camera_record(world: World, file: str, elevation_deg: float, azimuth_deg: float) -> dict:
    rig = world.rig
    return {
        "file": file,
        "elevation_deg": float(elevation_deg),
        "azimuth_deg": float(azimuth_deg),
        "camera_to_world": camera_to_turntable(elevation_deg, azimuth_deg, rig).tolist(),
        "K": rig.intrinsics().tolist(),
        "distortion": world.lens.to_dict(),
        "width": rig.width,
        "height": rig.height,
    }


def _read_cameras(path: Path) -> list[dict]:
    if not path.exists():
        return []
    try:
        frames = json.loads(path.read_text(encoding="utf-8"))["frames"]
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ScanFolderError(f"{path}: not a sim_truth cameras file ({exc})") from exc
    if not isinstance(frames, list):
        raise ScanFolderError(f"{path}: 'frames' is not a list")
    return frames


def write_truth_mesh(scan_root: Path, world: World) -> None:
    """The true stone as PLY, in the turntable frame, metres."""
    mesh_path = _truth_paths(scan_root)[0]
    atomic_write_with(mesh_path, lambda tmp: world.stone.mesh.export(tmp, file_type="ply"))


@dataclass(frozen=True)
class TruthFrame:
    """One frame's truth to write: where the camera was, and its mask and image from the render that made the
    frame (None: rendered here at this pose; plates get an empty mask, as the stone was not there)."""

    file: str
    elevation_deg: float
    azimuth_deg: float
    mask: np.ndarray | None = None  # [H, W] bool
    image: TruthImage | None = None


def write_truth_frame(
    scan_root: Path,
    world: World,
    file: str,
    elevation_deg: float,
    azimuth_deg: float,
    mask: np.ndarray | None = None,
    image: TruthImage | None = None,
) -> None:
    """Add or replace one frame's camera, true mask and truth image; writes mesh.ply first if it is missing."""
    write_truth_frames(scan_root, world, [TruthFrame(file, elevation_deg, azimuth_deg, mask, image)])


def write_truth_frames(scan_root: Path, world: World, frames: Sequence[TruthFrame]) -> None:
    """Add or replace these frames' cameras, true masks and truth images; writes mesh.ply first if it is missing.

    cameras.json is rewritten once for all of them: frame by frame, a 246-frame scan rewrote it 246 times."""
    scan_root = Path(scan_root)
    scan = ScanFolder(scan_root)
    for frame in frames:
        scan.resolve_inside(frame.file)
    mesh_path, cameras_path, _ = _truth_paths(scan_root)
    if not mesh_path.exists():
        write_truth_mesh(scan_root, world)
    for frame in frames:
        mask, image = frame.mask, frame.image
        if mask is None:
            out = render(world, frame.elevation_deg, frame.azimuth_deg, supersample=2)
            mask, image = out.mask, TruthImage.of(out)
        if image is not None:
            write_truth_image(image_path_for(scan_root, frame.file), image)
        if mask.shape != (world.rig.height, world.rig.width):
            raise ScanFolderError(f"{frame.file}: mask is {mask.shape}, the rig makes {world.rig.height}x{world.rig.width}")
        png = Image.fromarray(np.where(mask, 255, 0).astype(np.uint8))
        atomic_write_with(mask_path_for(scan_root, frame.file), lambda tmp, png=png: png.save(tmp, format="PNG"))
    written = {frame.file for frame in frames}
    records = [f for f in _read_cameras(cameras_path) if f.get("file") not in written]
    records += [_camera_record(world, f.file, f.elevation_deg, f.azimuth_deg) for f in frames]
    atomic_write_json(cameras_path, {"frames": sorted(records, key=lambda f: str(f["file"]))})


def write_sim_truth(scan_root: Path, world: World, frames: Sequence[Frame]) -> None:
    """Write the whole sim_truth/ for `frames` at once (masks rendered with the stone in place)."""
    scan_root = Path(scan_root)
    for file, _, _ in frames:
        ScanFolder(scan_root).resolve_inside(file)
    mesh_path, cameras_path, _ = _truth_paths(scan_root)
    write_truth_mesh(scan_root, world)
    for file, elevation, azimuth in frames:
        out = render(world, elevation, azimuth, stone_present=True, supersample=2)
        mask = out.mask
        write_truth_image(image_path_for(scan_root, file), TruthImage.of(out))
        png = Image.fromarray(np.where(mask, 255, 0).astype(np.uint8))
        atomic_write_with(mask_path_for(scan_root, file), lambda tmp, png=png: png.save(tmp, format="PNG"))
    records = [_camera_record(world, file, elev, azim) for file, elev, azim in frames]
    atomic_write_json(cameras_path, {"frames": sorted(records, key=lambda f: str(f["file"]))})
