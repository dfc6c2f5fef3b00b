"""Export stage: a trained scan folder becomes asset/ (splats, infill, mesh, metrics, gate, report).

The 'trained' scan is built in seconds: the surface model is hand-placed, three staggered layers
of opaque flat discs on the true surface of a procedural stone (coloured by its albedo), and the
photos are that model's own renders, so it plays a perfectly trained model. Its infill is built
from it by the NGS infill builder, as training would.
"""

from __future__ import annotations

import json
from dataclasses import replace
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from sim.stone import procedural_stone
from station.errors import BadInputError
from station.export.mesh import check_mesh
from station.export.splat_formats import read_splat
from station.export.splat_model import matrix_to_quat
from station.export.stage import ExportConfig, ExportReport, export_scan, splat_model_of
from station.ngs.conventions import rgb_to_sh
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Camera, InfillConfig, build_infill
from station.ngs.raster import rasterization
from station.process.images_io import srgb_to_linear, write_mask_png, write_png16
from station.formats.transforms import PinholeCamera
from station.process.transforms import PosedFrame, Transforms, write_transforms
from station.rig_geometry import RigGeometry, camera_to_turntable
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with

SIZE = (160, 120)
ELEVATIONS = (10.0, 35.0, 60.0)
AZIMUTHS = 8
SIGMA = 0.8  # disc standard deviation, in sample spacings
DEPTHS = (0.0, 0.3, 0.6)  # layers below the surface, in sample spacings; each layer's gaps differ
INFILL = InfillConfig(levels=(16, 32), erosion_iters=(2, 2), prune_downscale=1)
FAST = ExportConfig(mesh_resolution=80, depth_views=12, truth_samples=5000, report_views=2, strip_views=4)
CONTRACT_KEYS = ("psnr", "ssim", "psnr_star", "ssim_star", "sos", "num_gaussians", "num_infill", "train_seconds")
ASSET_FILES = ("splat.ply", "infill.ply", "splat.splat", "splat.spz", "splat.glb", "mesh.ply", "mesh.glb",
               "metrics.json", "gate.json", "report.html")


def disc_surface(mesh: trimesh.Trimesh, albedo, n: int, opacity: float) -> Gaussians:
    """Flat discs tangent to the surface, in staggered layers; degree-1 SH with no view dependence."""
    spacing = np.sqrt(mesh.area / n)
    layers = [trimesh.sample.sample_surface_even(mesh, n, seed=k) for k in range(len(DEPTHS))]
    points = np.concatenate([p - d * spacing * mesh.face_normals[f] for (p, f), d in zip(layers, DEPTHS)])
    faces = np.concatenate([f for _, f in layers])
    quats = []
    for normal in mesh.face_normals[faces]:
        x = np.cross(normal, [0.3, 0.5, 0.8])
        x /= np.linalg.norm(x)
        quats.append(matrix_to_quat(np.stack([x, np.cross(normal, x), normal], 1)))
    sigma = SIGMA * spacing
    m = len(points)
    rgb = torch.as_tensor(np.clip(albedo(points), 0.02, 0.98), dtype=torch.float32)  # [M, 3]
    return Gaussians({
        "means": torch.as_tensor(points, dtype=torch.float32),
        "scales": torch.log(torch.tensor([sigma, sigma, 0.1 * sigma], dtype=torch.float32)).expand(m, 3).clone(),
        "quats": torch.as_tensor(np.array(quats), dtype=torch.float32),
        "opacities": torch.full((m,), math.log(opacity / (1 - opacity))),
        "sh0": rgb_to_sh(rgb)[:, None, :],
        "shN": torch.zeros(m, 3, 3),
    })


def save_surface(scan: ScanFolder, model: Gaussians) -> None:
    data = {"params": model.state_dict(), "sh_degree": 1, "scene_scale": 0.5, "downscale": 1, "method": "ngs"}
    atomic_write_with(scan.model_dir / "surface.pt", lambda tmp: torch.save(data, tmp))


def build_scan(root: Path, seed: int = 3, n_per_layer: int = 4000) -> ScanFolder:
    """Posed images + masks of an opaque disc model, its infill, train metrics and the true mesh."""
    scan = ScanFolder(root)
    stone = procedural_stone(seed, size_m=0.08)
    rig = RigGeometry().scaled(*SIZE)
    intr = PinholeCamera(SIZE[0], SIZE[1], rig.focal_px, rig.focal_px, SIZE[0] / 2, SIZE[1] / 2)
    model = disc_surface(stone.mesh, stone.albedo, n_per_layer, opacity=0.995)
    g = {k: v.detach() for k, v in model.activated().items()}
    c2ws = np.array([camera_to_turntable(e, a * 360.0 / AZIMUTHS, rig) for e in ELEVATIONS for a in range(AZIMUTHS)])
    viewmats = torch.as_tensor(np.linalg.inv(c2ws), dtype=torch.float32)  # [V, 4, 4]
    Ks = torch.as_tensor(intr.matrix(), dtype=torch.float32).expand(len(c2ws), 3, 3)
    with torch.no_grad():
        rgb, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                      viewmats, Ks, SIZE[0], SIZE[1], sh_degree=1)  # [V, H, W, 3], [V, H, W, 1]
    frames = []
    for k, c2w in enumerate(c2ws):
        name = f"v{k:03d}.png"
        write_png16(scan.images_dir / name, srgb_to_linear(rgb[k].clamp(0, 1).numpy()))
        write_mask_png(scan.masks_dir / name, alpha[k, ..., 0].numpy() > 0.5)
        frames.append(PosedFrame(f"images/{name}", c2w, f"masks/{name}"))
    write_transforms(scan, Transforms(intr, frames))
    save_surface(scan, model)
    cameras = [Camera(viewmats[k], Ks[k], SIZE[0], SIZE[1]) for k in range(len(c2ws)) if k % 8]  # training views
    infill = build_infill(g, cameras, INFILL)
    atomic_write_with(scan.model_dir / "infill.pt", lambda tmp: torch.save(infill.state_dict(), tmp))
    losses = [{"step": s, "seconds": s / 50, "loss": 0.2 * math.exp(-s / 400) + 0.01, "image": 0.2 * math.exp(-s / 400)}
              for s in range(100, 1100, 100)]
    atomic_write_json(scan.model_dir / "train_metrics.json", {
        "report": {"method": "ngs", "steps": 1000, "seconds": 20.0, "num_gaussians": len(model), "num_infill": len(infill)},
        "config": {"ngs": {"infill": {"levels": list(INFILL.levels), "erosion_iters": list(INFILL.erosion_iters)}}},
        "losses": losses,
    })
    atomic_write_with(scan.sim_truth_dir / "mesh.ply", lambda tmp: stone.mesh.export(tmp, file_type="ply"))
    return scan


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> ScanFolder:
    return build_scan(tmp_path_factory.mktemp("scan") / "stone")


@pytest.fixture(scope="module")
def opaque(built: ScanFolder) -> ExportReport:
    """The opaque scan exported once; a stale quarantine marker from an 'earlier run' sits in asset/."""
    atomic_write_with(built.asset_dir / "QUARANTINED.txt", lambda tmp: tmp.write_text("stale"))
    report = export_scan(built.root, replace(FAST, reference_mesh=built.sim_truth_dir / "mesh.ply"))
    print(f"\nexport of the opaque stone: {report.seconds:.1f} s; "
          f"{json.dumps({k: v for k, v in report.metrics.items() if k != 'views'}, default=str)}")
    return report


def export_with_opacity(built: ScanFolder, root: Path, opacity: float, keep_asset: bool = False) -> ExportReport:
    """Export a copy of the scan whose surface opacities are all `opacity`; `keep_asset` copies an
    earlier run's asset/ along."""
    shutil.copytree(built.root, root, ignore=shutil.ignore_patterns("stages", *(() if keep_asset else ("asset",))))
    scan = ScanFolder(root)
    state = torch.load(scan.model_dir / "surface.pt", weights_only=True)["params"]
    state["opacities"] = torch.full_like(state["opacities"], math.log(opacity / (1 - opacity)))
    save_surface(scan, Gaussians.from_state_dict(state))
    return export_scan(root, FAST)


@pytest.fixture(scope="module")
def transparent(built: ScanFolder, tmp_path_factory) -> ExportReport:
    """A see-through model: every surface opacity 0.05."""
    return export_with_opacity(built, tmp_path_factory.mktemp("transparent") / "stone", 0.05)


def test_every_asset_file_is_written(opaque: ExportReport):
    asset = opaque.scan_root / "asset"
    for name in ASSET_FILES:
        assert (asset / name).is_file(), name
        assert opaque.files[name] == asset / name
    assert not list(asset.glob("*.tmp*"))


def test_the_splat_files_reload_as_the_trained_surface_less_the_trimmed(opaque: ExportReport, built: ScanFolder):
    surface = Gaussians.from_state_dict(torch.load(built.model_dir / "surface.pt", weights_only=True)["params"])
    trained = splat_model_of(surface)
    ply = read_splat(opaque.files["splat.ply"])
    assert ply.num == opaque.metrics["shipped_splat"]["shipped_gaussians"] <= trained.num
    index = {tuple(row): i for i, row in enumerate(trained.means.tolist())}
    expected = trained.subset(np.array([index[tuple(row)] for row in ply.means.tolist()], dtype=np.int64))
    for name in ("means", "scales_log", "opacity_logit", "sh_dc"):
        np.testing.assert_array_equal(getattr(ply, name), getattr(expected, name), err_msg=name)
    np.testing.assert_allclose(ply.quats, expected.quats, atol=1e-6)
    np.testing.assert_allclose(ply.sh_rest, expected.sh_rest, atol=1e-5)
    for name in ("splat.splat", "splat.spz", "splat.glb"):
        assert read_splat(opaque.files[name]).num == ply.num, name


def test_the_infill_ply_is_opaque_grey_and_counts_the_infill(opaque: ExportReport):
    infill = read_splat(opaque.files["infill.ply"])
    assert infill.num == opaque.metrics["num_infill"] > 0
    assert infill.opacity().min() > 0.999
    np.testing.assert_allclose(infill.rgb(), 0.5, atol=1e-6)


def test_the_mesh_reloads_watertight_and_matches_the_true_stone(opaque: ExportReport, built: ScanFolder):
    mesh = trimesh.load_mesh(opaque.files["mesh.ply"])
    assert check_mesh(mesh).ok
    geometry = opaque.metrics["geometry"]
    truth = trimesh.load_mesh(built.sim_truth_dir / "mesh.ply")
    assert geometry["true_volume_m3"] == pytest.approx(truth.volume)
    # A hand-placed disc splat, not a trained one: its rendered depth sits about a disc's size
    # towards the camera, so these bounds are looser than the targets for trained models.
    assert abs(geometry["volume_rel_error"]) < 0.15
    assert geometry["chamfer_fraction_of_diagonal"] < 0.015
    assert geometry["fscore"] > 0.5


def test_metrics_json_holds_the_contract_keys(opaque: ExportReport):
    metrics = json.loads(opaque.files["metrics.json"].read_text())
    for key in CONTRACT_KEYS + ("mesh_volume_m3", "mesh_area_m2", "mesh_watertight", "mesh_manifold",
                                "infill_volume_m3", "outside_hull_fraction", "geometry"):
        assert key in metrics, key
    assert metrics["lpips"] == "skipped"
    assert metrics["train_seconds"] == 20.0
    assert metrics["num_gaussians"] == len(DEPTHS) * 4000
    assert metrics["mesh_volume_m3"] > 0 and metrics["mesh_area_m2"] > 0
    assert metrics["infill_volume_m3"] == pytest.approx(metrics["geometry"]["true_volume_m3"], rel=0.1)


def test_an_opaque_model_passes_the_gate_and_clears_an_old_quarantine(opaque: ExportReport):
    gate = json.loads(opaque.files["gate.json"].read_text())
    assert opaque.passed and gate["pass"] is True, opaque.gate.summary()
    assert {c["name"] for c in gate["checks"]} == {"SOS", "PSNR", "SSIM", "mesh", "volume_consistency", "visual_hull"}
    for check in gate["checks"]:
        assert set(check) >= {"name", "value", "threshold", "pass"}
    assert not (opaque.scan_root / "asset" / "QUARANTINED.txt").exists()
    assert json.loads((opaque.scan_root / "stages" / "export.json").read_text())["pass"] is True


def test_a_transparent_model_is_written_but_quarantined_for_its_sos(transparent: ExportReport):
    asset = transparent.scan_root / "asset"
    assert not transparent.passed
    gate = json.loads((asset / "gate.json").read_text())
    sos = next(c for c in gate["checks"] if c["name"] == "SOS")
    assert gate["pass"] is False and sos["pass"] is False and sos["value"] < 0.9
    quarantine = (asset / "QUARANTINED.txt").read_text()
    assert "SOS" in quarantine and "see-through" in quarantine
    for name in ("splat.ply", "infill.ply", "splat.splat", "splat.spz", "splat.glb", "metrics.json", "report.html"):
        assert (asset / name).is_file(), name
    assert "QUARANTINED" in (asset / "report.html").read_text()


def test_a_model_too_faint_to_mesh_is_quarantined_for_its_mesh_and_leaves_no_mesh_file(
    opaque: ExportReport, built: ScanFolder, tmp_path: Path
):
    assert (built.asset_dir / "mesh.ply").is_file()  # the copy starts with an earlier run's mesh
    report = export_with_opacity(built, tmp_path / "faint", 0.002, keep_asset=True)
    mesh = next(c for c in report.gate.checks if c.name == "mesh")
    assert not report.passed and not mesh.passed
    assert any("no mesh could be built" in p for p in report.metrics["mesh_problems"])
    assert not (report.scan_root / "asset" / "mesh.ply").exists() and "mesh.ply" not in report.files
    assert "mesh" in (report.scan_root / "asset" / "QUARANTINED.txt").read_text()


def test_the_report_is_self_contained_and_shows_the_verdict(opaque: ExportReport):
    text = opaque.files["report.html"].read_text()
    assert "PASS" in text and "QUARANTINED" not in text
    assert "http://" not in text and "https://" not in text and "<script" not in text
    sources = re.findall(r'src="([^"]*)"', text)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert "<polyline" in text


def test_export_without_a_trained_model_names_the_missing_file(tmp_path: Path):
    with pytest.raises(BadInputError, match="surface.pt"):
        export_scan(tmp_path, FAST)

