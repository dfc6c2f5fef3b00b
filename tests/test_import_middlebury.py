"""`station import --format middlebury` and `--masks dark-backdrop`: a synthetic set, bad sets, the real temple ring."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from typer.testing import CliRunner

from station.cli import app
from station.errors import BadInputError, FormatError
from station.process.backdrop_masks import dark_backdrop_mask
from station.process.importers import ImportSettings, import_dataset, read_middlebury
from station.process.transforms import read_transforms
from station.process.visual_hull import ring_frame
from station.rig_geometry import look_at_c2w
from station.scanfolder import ScanFolder

W, H, F = 80, 60, 90.0
K = np.array([[F, 0.0, 41.5], [0.0, F + 1.0, 29.0], [0.0, 0.0, 1.0]])
DISTANCE, ELEVATION = 0.6, np.deg2rad(25.0)  # metres, radians
CENTRE, RADIUS = np.array([0.02, -0.01, 0.05]), 0.12  # the blob: a ball, metres
TILT = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.4), -np.sin(0.4)], [0.0, np.sin(0.4), np.cos(0.4)]])  # ring normal off z
LIGHT = np.array([0.0, 0.0, 1.0])  # in the ring's own frame: one side of the ball is in shadow
QUICK = ImportSettings(hull_resolution=24, masks="dark-backdrop")
TEMPLE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "multiview" / "templeSparseRing"
TEMPLE_BOX = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])  # its README, metres


def ring_c2ws(count: int = 6) -> list[np.ndarray]:
    """OpenCV camera-to-world poses on a ring around CENTRE whose normal is TILT's z, source metres."""
    out = []
    for a in np.linspace(0.0, 2 * np.pi, count, endpoint=False):
        local = DISTANCE * np.array([np.cos(ELEVATION) * np.cos(a), np.cos(ELEVATION) * np.sin(a), np.sin(ELEVATION)])
        out.append(look_at_c2w(CENTRE + TILT @ local, CENTRE, up=TILT[:, 2]))
    return out


def ball_silhouette_and_image(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ball's true silhouette [H, W] and an RGB image of it, lit from one side, on black."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = c2w[:3, 3] - CENTRE
    b = d @ oc
    disc = b * b - (oc @ oc - RADIUS**2)
    hit = disc > 0
    point = c2w[:3, 3] + (-b - np.sqrt(np.maximum(disc, 0)))[..., None] * d
    shade = np.clip(((point - CENTRE) / RADIUS) @ (TILT @ LIGHT), 0.0, 1.0)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[hit] = (np.array([1.0, 0.85, 0.6]) * (45 + 200 * shade[hit, None])).astype(np.uint8)
    return hit, rgb


def par_line(name: str, k: np.ndarray, c2w: np.ndarray) -> str:
    r = c2w[:3, :3].T
    t = -r @ c2w[:3, 3]
    return " ".join([name, *(f"{x:.17g}" for x in (*k.ravel(), *r.ravel(), *t))])


def write_middlebury(src: Path, cams: list[np.ndarray], setname: str = "blobSR") -> list[np.ndarray]:
    """A Middlebury set as published (count line first, one camera a line); the true silhouettes."""
    src.mkdir(parents=True)
    lines, silhouettes = [str(len(cams))], []
    for i, c2w in enumerate(cams):
        hit, rgb = ball_silhouette_and_image(c2w)
        Image.fromarray(rgb).save(src / f"{setname}{i + 1:04d}.png")
        lines.append(par_line(f"{setname}{i + 1:04d}.png", K, c2w))
        silhouettes.append(hit)
    (src / f"{setname}_par.txt").write_text("\n".join(lines) + "\n")
    return silhouettes


def set_line(src: Path, number: int, text: str) -> None:
    par = src / "blobSR_par.txt"
    lines = par.read_text().splitlines()
    lines[number - 1] = text
    par.write_text("\n".join(lines) + "\n")


def test_cameras_land_where_they_were_put_and_masks_cover_the_blob(tmp_path):
    cams = ring_c2ws()
    silhouettes = write_middlebury(tmp_path / "src", cams)
    report = import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan", QUICK)
    assert (report.frames, report.masks, report.orient, report.units_to_m) == (6, "dark-backdrop", "ring", 1.0)
    scan = ScanFolder(tmp_path / "scan")
    transforms = read_transforms(scan)
    intr = transforms.intrinsics
    assert (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy) == (W, H, F, F + 1.0, 41.5, 29.0)
    # "ring": origin where the cameras look (the ball), z along the ring's normal, cameras above.
    centres = np.array([f.c2w[:3, 3] for f in transforms.frames])
    np.testing.assert_allclose(centres[:, 2], DISTANCE * np.sin(ELEVATION), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2], axis=1), DISTANCE * np.cos(ELEVATION), atol=1e-6)
    given = np.array([c[:3, 3] for c in cams])
    np.testing.assert_allclose(np.linalg.norm(centres[:, None] - centres[None], axis=-1),
                               np.linalg.norm(given[:, None] - given[None], axis=-1), atol=1e-6)
    for frame, hit in zip(transforms.frames, silhouettes):
        np.testing.assert_allclose(frame.c2w[:3, 2], -frame.c2w[:3, 3] / DISTANCE, atol=1e-6)  # looks at the origin
        mask = np.asarray(Image.open(scan.resolve_inside(frame.mask_path))) > 127
        assert mask[hit].mean() > 0.97, "the shadowed side of the blob must stay inside its mask"
        assert (mask & hit).sum() / (mask | hit).sum() > 0.9
    assert report.init_cloud == "visual_hull"


def test_keep_orient_gives_the_source_cameras_unchanged(tmp_path):
    cams = ring_c2ws(count=4)
    write_middlebury(tmp_path / "src", cams)
    import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan", ImportSettings(orient="keep", hull_resolution=24))
    transforms = read_transforms(ScanFolder(tmp_path / "scan"))
    assert all(f.mask_path is None for f in transforms.frames)  # masks="none" stays the default
    for frame, c2w in zip(transforms.frames, cams):
        np.testing.assert_allclose(frame.c2w, c2w, atol=1e-6)


def test_cli_imports_with_derived_masks_and_refuses_an_unknown_mask_mode(tmp_path):
    write_middlebury(tmp_path / "src", ring_c2ws(count=4))
    runner = CliRunner()
    ok = runner.invoke(app, ["import", str(tmp_path / "src"), "--format", "middlebury", "--out", str(tmp_path / "scan"),
                             "--masks", "dark-backdrop", "--json"])
    assert ok.exit_code == 0, ok.output
    assert json.loads(ok.stdout)["masks"] == "dark-backdrop"
    bad = runner.invoke(app, ["import", str(tmp_path / "src"), "--format", "middlebury", "--out", str(tmp_path / "b"),
                              "--masks", "grabcut"])
    assert bad.exit_code == 2 and "grabcut" in bad.output and "Traceback" not in bad.output


def test_dark_backdrop_masks_work_for_other_formats_without_masks(tmp_path):
    from test_import import ball_rgba, ring_cameras, write_colmap

    cams = ring_cameras(count=4)
    write_colmap(tmp_path / "src", cams)  # a ball on a dark grey backdrop, no masks
    report = import_dataset(tmp_path / "src", "colmap", tmp_path / "scan", ImportSettings(orient="keep", masks="dark-backdrop"))
    assert report.masks == "dark-backdrop" and report.init_cloud == "source"
    scan = ScanFolder(tmp_path / "scan")
    for frame, c2w in zip(read_transforms(scan).frames, cams):
        mask, ball = np.asarray(Image.open(scan.resolve_inside(frame.mask_path))) > 127, ball_rgba(c2w)[..., 3] > 0
        assert (mask & ball).sum() / (mask | ball).sum() > 0.95


def test_dark_backdrop_mask_keeps_shadow_and_holes_seen_through_drops_cloth_and_fills_crevices():
    rgb = np.zeros((120, 160, 3), np.uint8)
    rgb[20:100, 20:140] = 200
    rgb[40:80, 40:90] = 0  # a window onto the backdrop, large against the object: stays open
    rgb[50:59, 110:119] = 0  # a crevice as dark as the backdrop, too wide for the closing: filled as a hole
    rgb[20:100, 60:68] = 60  # a shadowed column, dimmer than the rest
    rgb[:, 140:] = 40  # lit cloth at the frame's side, as dim as the column, touching the object
    mask = dark_backdrop_mask(rgb) > 0
    assert not mask[45:75, 45:58].any() and mask[50:59, 110:119].all() and mask[20:100, 60:68].all()
    assert not mask[:10].any() and not mask[:, :10].any() and not mask[:, 143:].any()


@pytest.mark.parametrize("spoil, match", [
    ("missing", "expected exactly one <set>_par.txt camera file, found none"),
    ("two", "found blobSR_par.txt, copy_par.txt"),
])
def test_the_camera_file_must_be_exactly_one(tmp_path, spoil, match):
    write_middlebury(tmp_path / "src", ring_c2ws(count=3))
    par = tmp_path / "src" / "blobSR_par.txt"
    if spoil == "missing":
        par.unlink()
    else:
        (tmp_path / "src" / "copy_par.txt").write_text(par.read_text())
    with pytest.raises(BadInputError, match=match):
        import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan")
    assert not (tmp_path / "scan").exists()


def fields(name: str = "blobSR0002.png", k: np.ndarray = K, r: np.ndarray = np.eye(3), t: str = "0 0 1") -> str:
    return " ".join([name, *(f"{x:.17g}" for x in (*k.ravel(), *r.ravel())), t])


SKEWED, LOWER, NEGATIVE = K + [[0, 3, 0], [0, 0, 0], [0, 0, 0]], K + [[0, 0, 0], [0, 0, 0], [5, 0, 0]], K * [[-1], [1], [1]]


@pytest.mark.parametrize("line, problem", [
    (fields(t="0 0"), "21 fields; expected 22"),
    (fields(t="0 0 one"), "not a number"),
    (fields(t="0 0 nan"), "NaN or infinity"),
    (fields(r=np.diag([1.1, 1.0, 1.0])), "R: upper 3x3 is not a rotation"),
    (fields(r=np.diag([-1.0, 1.0, 1.0])), "R: upper 3x3 is not a rotation .mirrored"),
    (fields(k=LOWER), "not upper triangular"),
    (fields(k=NEGATIVE), "focal lengths k11, k22 must be positive"),
    (fields(k=SKEWED), "skew"),
    (fields(k=K * [[1.01], [1.01], [1]]), "K differs from line 2's"),
    (fields("blobSR0001.png"), "already given on line 2"),
    (fields("../outside.png"), "resolves outside the source folder"),
    (fields("blobSR0009.png"), "not found"),
])
def test_a_malformed_camera_line_is_refused_naming_file_and_line(tmp_path, line, problem):
    write_middlebury(tmp_path / "src", ring_c2ws(count=3))
    (tmp_path / "outside.png").write_bytes((tmp_path / "src" / "blobSR0001.png").read_bytes())
    set_line(tmp_path / "src", 3, line)
    with pytest.raises(FormatError, match=f"blobSR_par.txt: line 3.*{problem}"):
        import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan")
    assert not (tmp_path / "scan").exists()


def test_a_frame_where_no_object_stands_out_is_refused_with_dark_backdrop_masks(tmp_path):
    write_middlebury(tmp_path / "src", ring_c2ws(count=3))
    Image.fromarray(np.full((H, W, 3), 5, np.uint8)).save(tmp_path / "src" / "blobSR0002.png")
    with pytest.raises(FormatError, match="blobSR0002.png: --masks dark-backdrop found no object"):
        import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan", QUICK)


def test_a_wrong_camera_count_and_an_image_linked_out_are_refused(tmp_path):
    write_middlebury(tmp_path / "src", ring_c2ws(count=3))
    set_line(tmp_path / "src", 1, "4")
    with pytest.raises(FormatError, match="blobSR_par.txt: line 1: says 4 cameras but 3"):
        import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan")
    set_line(tmp_path / "src", 1, "3")
    image = tmp_path / "src" / "blobSR0002.png"
    image.rename(tmp_path / "moved.png")
    image.symlink_to(tmp_path / "moved.png")
    with pytest.raises(FormatError, match="blobSR_par.txt: line 3: 'blobSR0002.png' resolves outside the source"):
        import_dataset(tmp_path / "src", "middlebury", tmp_path / "scan")
    assert not (tmp_path / "scan").exists()


@pytest.mark.shared_data
def test_real_temple_ring_imports_on_a_ring_with_plausible_masks(tmp_path):
    if not TEMPLE.is_dir():
        pytest.skip("shared data absent")
    report = import_dataset(TEMPLE, "middlebury", tmp_path / "scan", ImportSettings(hull_resolution=48,
                                                                                    masks="dark-backdrop"))
    assert (report.frames, report.masks, report.orient) == (16, "dark-backdrop", "ring")
    scan = ScanFolder(tmp_path / "scan")
    transforms = read_transforms(scan)
    assert (transforms.intrinsics.width, transforms.intrinsics.height) == (640, 480)
    centres = np.array([f.c2w[:3, 3] for f in transforms.frames])
    radius = np.linalg.norm(centres[:, :2], axis=1)
    assert 0.4 < radius.mean() < 0.8 and radius.std() < 0.02 * radius.mean(), radius
    assert centres[:, 2].min() > 0 and np.ptp(centres[:, 2]) < 0.01  # one ring, above the temple, metres
    fractions = [(np.asarray(Image.open(scan.resolve_inside(f.mask_path))) > 127).mean() for f in transforms.frames]
    assert 0.1 < min(fractions) and max(fractions) < 0.4, fractions
    # Cameras and masks agree with the set's README: the hull they carve, back in the source's frame (the
    # importer's declared axis change undone), spans the temple's published bounding box.
    rot, origin = ring_frame([f.c2w for f in read_middlebury(TEMPLE).frames])
    hull = np.asarray(trimesh.load(scan.root / "poses" / "points3d.ply", process=False).vertices) @ rot + origin
    np.testing.assert_allclose(hull.min(0), TEMPLE_BOX[0], atol=0.015)
    np.testing.assert_allclose(hull.max(0), TEMPLE_BOX[1], atol=0.015)
