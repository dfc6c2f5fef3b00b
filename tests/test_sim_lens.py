"""The simulated lens (distortion, vignetting, exposure jitter) is in the raws, and the pipeline takes it out."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from sim.lens import SimLens
from sim.rig import direct_scan, make_stone
from sim.scene import World, render
from sim.stone import Stone, procedural_stone
from sim.truth import image_path_for, read_truth_image
from station.process.develop import DevelopSettings, develop_raw
from station.process.develop_stage import ProcessSettings, develop_scan
from station.process.images_io import read_png16, write_png16
from station.formats.transforms import PinholeCamera
from station.process.lens import Lens, pinhole_for, undistortion
from station.process.photometry import FlatField, fit_flat_field
from station.process.poses import PoseSettings, pose_scan
from station.process.rig_model import RigModel
from station.process.transforms import read_transforms
from station.rig_geometry import RigGeometry
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_json

SMALL = RigGeometry().scaled(320, 240)
RINGS = (15.0, 45.0)


def _wall() -> Stone:
    """A dark wall across the view at 10 deg tilt whose straight top edge runs near the top of the frame."""
    mesh = trimesh.creation.box(extents=(0.02, 0.8, 0.115))
    mesh.apply_translation((-0.05, 0.0, 0.0575))
    return Stone(mesh, lambda points: np.full((len(points), 3), 0.1), 0.0, "wall")


def _edge_rows(luminance: np.ndarray) -> np.ndarray:
    """Per column, the sub-pixel row where the bright backdrop falls to the dark wall: the crossing of the
    level halfway between the two just above and just below the edge (the backdrop has its own gradient)."""
    rows = []
    for column in luminance.T:
        step = int(np.argmin(np.diff(column)))
        half = (np.median(column[step - 12:step - 4]) + np.median(column[step + 5:step + 13])) / 2.0
        i = step - 4 + int(np.flatnonzero(column[step - 4:step + 5] < half)[0])
        rows.append(i - 1 + (column[i - 1] - half) / (column[i - 1] - column[i]) + 0.5)
    return np.array(rows)


def _wall_image(lens: SimLens, root: Path) -> np.ndarray:
    """The wall's raw through `lens`, developed: linear luminance [480, 640]."""
    scan = direct_scan(root, _wall(), RigGeometry().scaled(640, 480), (10.0,), 1, lens=lens)
    return develop_raw(scan.root / "raw/e0_a000.dng", DevelopSettings(demosaic="LINEAR")).linear


def _sagitta(image: np.ndarray) -> float:
    """How far the wall's straight top edge bows from a line across the image [H, W, 3], in pixels."""
    band = image.mean(axis=2)[10:120, 20:-20]  # the edge, near the top of the frame, away from its sides
    rows = _edge_rows(band)
    columns = np.arange(len(rows)) - len(rows) / 2.0
    return float(abs(np.polyfit(columns, rows, 2)[0]) * (len(rows) / 2.0) ** 2)


@pytest.fixture(scope="module")
def wall(tmp_path_factory) -> np.ndarray:
    return _wall_image(SimLens(), tmp_path_factory.mktemp("wall"))


def test_a_straight_edge_bends_in_the_raw_through_the_lens_and_not_through_a_pinhole(wall, tmp_path):
    straight = _sagitta(_wall_image(SimLens(distortion=False), tmp_path))
    assert _sagitta(wall) > 1.0 and straight < 0.1, (_sagitta(wall), straight)  # measured: 1.27 and < 0.01 px


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    """A 2 x 4 scan of the default stone at 320x240 through the default lens, and its develop."""
    raw = direct_scan(tmp_path_factory.mktemp("raw"), make_stone(None), SMALL, RINGS, 4)
    developed = ScanFolder(tmp_path_factory.mktemp("developed") / "scan")
    shutil.copytree(raw.root, developed.root)
    return raw, developed, develop_scan(developed, ProcessSettings())


def _view_gain(image: np.ndarray, exposed: np.ndarray, where: np.ndarray) -> float:
    """Median luminance ratio of a developed image to the truth over `where` [H, W]."""
    return float(np.median(image.mean(axis=2)[where] / np.maximum(exposed.mean(axis=2)[where], 1e-4)))


def _shot_gains(scan: ScanFolder, develop) -> dict[str, float]:
    """Each shot's exposure against the truth on the backdrop and plate (the stone left out), per `develop`."""
    gains = {}
    for entry in (e for e in scan.read_manifest() if e.kind == "shot"):
        truth = read_truth_image(image_path_for(scan.root, entry.file))
        gains[entry.file] = _view_gain(develop(entry), truth.exposed, truth.alpha == 0)
    return gains


def test_shots_differ_in_gain_in_the_raws_and_the_develop_brings_them_to_one_exposure(small_scan):
    raw, developed, _ = small_scan
    wb = DevelopSettings(demosaic="LINEAR")
    as_shot = _shot_gains(raw, lambda e: develop_raw(raw.root / e.file, wb).linear)
    as_developed = _shot_gains(developed, lambda e: read_png16(developed.images_dir / f"{Path(e.file).stem}.png"))
    for ring in ("e0_", "e1_"):
        shot = [g for f, g in as_shot.items() if ring in f]
        done = [g for f, g in as_developed.items() if ring in f]
        assert max(shot) / min(shot) > 1.03, shot  # the shutter scatters a few percent
        assert max(done) / min(done) < 1.004, done  # within a ring the develop matches every shot to its plate


def _corner_to_centre(image: np.ndarray, exposed: np.ndarray, valid: np.ndarray) -> float:
    """Light in the frame's corners over light in its centre, against the truth (the scene's own shading out),
    over the `valid` [H, W] pixels."""
    h, w = valid.shape
    k = h // 8
    corners = np.zeros((h, w), bool)
    corners[:k, :k] = corners[:k, -k:] = corners[-k:, :k] = corners[-k:, -k:] = True
    centre = np.zeros((h, w), bool)
    centre[h // 2 - k:h // 2 + k, w // 2 - k:w // 2 + k] = True
    return _view_gain(image, exposed, corners & valid) / _view_gain(image, exposed, centre & valid)


def test_corners_are_darker_in_the_raw_and_the_develop_flattens_them(small_scan):
    raw, developed, report = small_scan
    truth = read_truth_image(image_path_for(raw.root, "raw/e1_a000.dng"))
    empty = truth.alpha == 0
    as_shot = develop_raw(raw.root / "raw/e1_a000.dng", DevelopSettings(demosaic="LINEAR")).linear
    as_developed = read_png16(developed.images_dir / "e1_a000.png")  # what training reads
    assert _corner_to_centre(as_shot, truth.exposed, empty) < 0.78  # 0.6 stops (0.66) down at the very corners
    assert abs(_corner_to_centre(as_developed, truth.exposed, empty) - 1.0) < 0.02
    assert report.vignetting_stops == pytest.approx(0.6, abs=0.05)


def test_the_flat_field_fit_ignores_the_scenes_own_edges_and_gradients():
    world = World(make_stone(None), rig=SMALL, lens=SimLens())
    falloff = SimLens().falloff(SMALL.height, SMALL.width)[..., None]
    plates = [render(world, e, 0.0, stone_present=False).radiance for e in (10.0, 36.0, 62.0)]
    fitted = fit_flat_field([p * falloff for p in plates]).at(SMALL.height, SMALL.width)[..., None]
    assert np.abs(fitted / falloff - 1.0).max() < 0.01
    assert abs(fit_flat_field(plates).corner_stops) < 0.02  # no vignetting: none is found
    assert FlatField().corner_stops == 0.0


# posing: the lens self-calibrated and undone, the rings brought to one exposure --------------------------
LENS_RIG = RigGeometry().scaled(480, 360)
RING_GAIN = 1.04  # the second ring's exposure error, left after the develop matched shots to plates


def _developed_lens_scan(root: Path, azimuths: int) -> tuple[ScanFolder, trimesh.Trimesh]:
    """A developed scan of a large speckled stone that fills the frame (features reach the corners) through the
    default lens, its second ring one exposure error off: what the develop hands to posing."""
    world = World(procedural_stone(11, size_m=0.26, look="speckled"), LENS_RIG, lens=SimLens())
    scan = ScanFolder(root)
    scan.images_dir.mkdir(parents=True)
    scan.masks_dir.mkdir()
    entries = []
    for i, elevation in enumerate(RINGS):
        for j in range(azimuths):
            azimuth, name = 360.0 * j / azimuths, f"e{i}_a{j:03d}"
            entries.append(ManifestEntry(f"raw/{name}.dng", "0" * 64, elevation, azimuth, "shot", 0.03, 100, ""))
            out = render(world, elevation, azimuth, supersample=1)
            write_png16(scan.images_dir / f"{name}.png", out.radiance * np.float32(RING_GAIN**i))
            Image.fromarray(out.mask.astype(np.uint8) * 255).save(scan.masks_dir / f"{name}.png")
    scan.write_manifest(entries)
    atomic_write_json(scan.scan_json, {"rig": LENS_RIG.to_dict(), "plan": {"elevations_deg": list(RINGS),
                                                                           "azimuths": azimuths}})
    return scan, world.stone.mesh


@pytest.fixture(scope="module")
def posed_lens_scan(tmp_path_factory):
    scan, mesh = _developed_lens_scan(tmp_path_factory.mktemp("lens") / "scan", azimuths=8)
    return scan, mesh, pose_scan(scan, PoseSettings(cross_check=False), RigModel.nominal(LENS_RIG, list(RINGS)))


def _surface_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    return cKDTree(mesh.sample(200_000, seed=0)).query(points)[0]


def test_posing_self_calibrates_the_lens_and_its_undistortion_straightens_the_edge(posed_lens_scan, wall):
    scan, _, report = posed_lens_scan
    assert report.lens["self_calibration"] == "refined" and report.lens["undistorted"]
    assert report.lens["k1"] < -0.05 and report.lens["max_shift_px"] > 2.0
    assert all(e < 0.25 for e in report.reprojection_by_ring_px.values())
    lens = Lens.from_dict(PinholeCamera(**report.lens["intrinsics"]), report.lens, "posed")
    assert read_transforms(scan).intrinsics == pinhole_for(lens)  # what training reads is that pinhole
    undistort = undistortion(lens.scaled(640, 480))
    assert undistort is not None and _sagitta(undistort.image(wall)) < 0.25  # measured: 0.07 px


def test_posing_brings_the_rings_to_one_exposure(posed_lens_scan):
    _, _, report = posed_lens_scan
    gains = report.ring_gains
    assert gains.get("45", 1.0) / gains.get("15", 1.0) == pytest.approx(1.0 / RING_GAIN, rel=0.004)
