"""`station export SCAN`: a trained scan folder's model/ becomes its asset/ folder.

Order matters for an unattended run: the old verdict goes first, then every asset file is written
(atomically) before the gate judges it, so a quarantined asset can still be inspected, and the
verdict files (gate.json, QUARANTINED.txt, report.html) come last. Re-running redoes every step
and overwrites; a quarantine marker left from an earlier run is removed only when the new verdict
passes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from station.errors import BadInputError
from station.export.gate import GateConfig, GateResult, evaluate_gate, write_gate
from station.export.geometry_metrics import compare_meshes, fraction_outside_visual_hull
from station.export.infill_occupancy import body_volume, infill_body
from station.export.mesh import (
    MeshConfig,
    VoxelGrid,
    build_watertight_mesh,
    opacity_mesh,
    render_depth_maps,
    resample_to_grid,
    vertex_colors_from_splats,
    write_mesh_files,
)
from station.export.report import ReportInputs, render_panels, write_report
from station.export.splat_formats import write_splat
from station.export.splat_model import SplatModel, logit
from station.export.trim import shipped_splat
from station.export.viewer_page import write_viewer
from station.ngs.dataset import SceneData, View, load_scene
from station.ngs.gaussians import Gaussians, rgb_to_sh
from station.ngs.infill import Camera, Infill
from station.ngs.sos import EVAL_INFILL, evaluate, load_surface, scan_infill
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_text

INFILL_GREY = 0.5


@dataclass
class ExportConfig:
    gate: GateConfig = field(default_factory=GateConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    mesh_resolution: int = 112  # voxels along the stone's longest side
    depth_views: int = 24  # training views rendered to depth for the TSDF (mesh.surface == "tsdf")
    depth_max_width: int = 200  # depth maps are rendered at most this wide: CPU rendering is the cost
    stl: bool = False  # also write asset/mesh.stl for printing
    reference_mesh: Path | None = None  # a known-true mesh (laser scan, simulator truth) to score the mesh against
    truth_samples: int = 20_000  # surface samples per mesh for the geometry errors
    report_views: int = 4  # held-out views shown in the report
    hull_tolerance: float = 0.01  # mask edge allowance of the floater check, as a share of the longer image side
    strip_views: int = 8  # views in the report's turntable strip


@dataclass
class ExportReport:
    scan_root: Path
    passed: bool
    gate: GateResult
    metrics: dict
    files: dict[str, Path]
    seconds: float

    def summary(self) -> str:
        verdict = "PASS" if self.passed else "QUARANTINED"
        return f"{self.scan_root}: {verdict} ({self.gate.summary()}) in {self.seconds:.1f} s"


def splat_model_of(surface: Gaussians) -> SplatModel:
    """The trained parameters as the writers' SplatModel (same parametrisation, numpy)."""
    p = {k: v.detach().cpu().numpy() for k, v in surface.params.items()}
    return SplatModel(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"][:, 0, :], p["shN"])


def infill_splat(infill: Infill) -> SplatModel:
    """The infill as its own splat: opaque, neutral grey, isotropic, degree 0."""
    m = len(infill)
    quats = np.zeros((m, 4), np.float32)
    quats[:, 0] = 1.0
    return SplatModel(
        infill.means.numpy(),
        np.log(infill.scales.numpy())[:, None].repeat(3, axis=1),
        quats,
        np.full(m, logit(np.array(1.0))),
        np.full((m, 3), rgb_to_sh(INFILL_GREY)),
        np.zeros((m, 0, 3)),
    )


def train_metrics(scan: ScanFolder) -> dict:
    """model/train_metrics.json, or {} for a model trained elsewhere."""
    path = scan.model_dir / "train_metrics.json"
    return scan.read_json(path) if path.is_file() else {}


def infill_erosion(train: dict, infill_source: str) -> int:
    """Fine cells the infill was eroded away from the surface: what its body must grow back."""
    if infill_source != "ngs":
        return int(EVAL_INFILL.erosion_iters[-1])
    iters = train.get("config", {}).get("ngs", {}).get("infill", {}).get("erosion_iters")
    if not isinstance(iters, list) or not iters or not isinstance(iters[-1], int) or iters[-1] < 0:
        raise BadInputError("model/train_metrics.json: config.ngs.infill.erosion_iters missing; cannot size the infill body")
    return int(iters[-1])


def _c2ws(views: list[View]) -> np.ndarray:
    return np.linalg.inv(np.stack([v.viewmat.double().numpy() for v in views]))  # [V, 4, 4]


def _spread(count: int, wanted: int) -> list[int]:
    """Up to `wanted` indices evenly spread over range(count)."""
    return sorted({int(i) for i in np.linspace(0, count - 1, min(wanted, count))}) if count else []


def mesh_splat(model: SplatModel, scene: SceneData, body: np.ndarray, body_grid: VoxelGrid, config: ExportConfig) -> tuple[trimesh.Trimesh, VoxelGrid]:
    """The splat's opacity level set (or the TSDF of its rendered depth) with the infill body inside;
    see station.export.mesh."""
    opaque = model.opacity() > 0.5
    means = model.means[opaque] if opaque.sum() >= 4 else model.means
    lo, hi = means.min(axis=0), means.max(axis=0)
    grid = VoxelGrid.around(lo, hi, float((hi - lo).max()) / config.mesh_resolution, pad_voxels=4)
    occupancy = resample_to_grid(body, body_grid, grid)
    # Marching cubes can leave zero-volume sliver bodies; trimesh divides 0/0 for their centre of
    # mass while extract_mesh ranks bodies by volume. The slivers are dropped, so the NaN is harmless.
    with np.errstate(invalid="ignore", divide="ignore"):
        if config.mesh.surface == "opacity":
            return opacity_mesh(model, occupancy, grid, config.mesh), grid
        views = [scene.train[i] for i in _spread(len(scene.train), config.depth_views)]
        factor = max(1, int(np.ceil(views[0].width / config.depth_max_width)))
        width, height = views[0].width // factor, views[0].height // factor
        Ks = np.stack([v.K.double().numpy() for v in views])  # [V, 3, 3]
        Ks[:, :2] /= factor
        c2ws = _c2ws(views)
        depths = render_depth_maps(model, c2ws, Ks, width, height, config.mesh)  # [V, H, W]
        return build_watertight_mesh(depths, Ks, c2ws, occupancy, grid, config.mesh), grid


def _write_mesh(model: SplatModel, scene: SceneData, body: np.ndarray, body_grid: VoxelGrid, config: ExportConfig,
                files: dict[str, Path], metrics: dict) -> trimesh.Trimesh | None:
    """Mesh the splat, write PLY/GLB(/STL), reload each and record its checks in `metrics`.

    A splat with no opaque surface (a see-through model) cannot be meshed: that is recorded as a
    failed mesh check for the gate, and stale mesh files of an earlier run are removed."""
    mesh_files = [files[name] for name in ("mesh.ply", "mesh.glb", "mesh.stl") if name in files]
    try:
        mesh, grid = mesh_splat(model, scene, body, body_grid, config)
    except BadInputError as exc:
        for path in mesh_files:
            path.unlink(missing_ok=True)
        for name in ("mesh.ply", "mesh.glb", "mesh.stl"):
            files.pop(name, None)
        metrics.update(mesh_watertight=False, mesh_manifold=False, mesh_volume_m3=None, mesh_area_m2=None,
                       mesh_files_ok=False, mesh_problems=[f"no mesh could be built: {exc}"])
        return None
    checks = write_mesh_files(mesh, files["mesh.ply"], files["mesh.glb"], files.get("mesh.stl"),
                              vertex_colors_from_splats(mesh.vertices, model))
    metrics.update(checks[str(files["mesh.ply"])].to_metrics())
    # Every written file is reloaded and checked: a file a downstream tool reads back broken fails the mesh check.
    metrics["mesh_problems"] = [f"{Path(path).name}: {p}" for path, check in checks.items() for p in check.problems()]
    metrics["mesh_files_ok"] = all(check.ok for check in checks.values())
    metrics["mesh_watertight"] = metrics["mesh_watertight"] and metrics["mesh_files_ok"]
    metrics["mesh_area_m2"] = float(mesh.area)
    metrics["mesh_voxel_m"] = grid.voxel_size
    return mesh


def _hull_fraction(model: SplatModel, scene: SceneData, config: ExportConfig) -> float | None:
    views = [v for v in scene.train + scene.test if v.mask is not None]
    if not views:
        return None
    masks = np.stack([v.mask.numpy() > 0.5 for v in views])  # [V, H, W]
    Ks = np.stack([v.K.double().numpy() for v in views])
    tolerance = max(2, round(config.hull_tolerance * max(masks.shape[1:])))
    return fraction_outside_visual_hull(model.means.astype(np.float64), masks, Ks, _c2ws(views), tolerance)


def _quarantine_text(scan: ScanFolder, gate: GateResult) -> str:
    lines = [f"QUARANTINED: {scan.root.name} failed the quality gate; the asset was written but must not ship.", ""]
    lines += [f"- {c.name}: {c.reason}" for c in gate.failures()]
    lines += ["", "Open asset/report.html for the renders, transmittance maps and every check.", ""]
    return "\n".join(lines)


def clear_verdict(scan: ScanFolder) -> None:
    """Remove the last verdict before anything else: a failed or killed export must not sit under an old pass."""
    (scan.asset_dir / "gate.json").unlink(missing_ok=True)
    scan.clear_done("export")


def export_scan(scan_root: Path | ScanFolder, config: ExportConfig | None = None) -> ExportReport:
    """Write asset/ (splats, infill, mesh, metrics, gate, report) from a trained scan folder."""
    config = config or ExportConfig()
    started = time.perf_counter()
    scan = scan_root if isinstance(scan_root, ScanFolder) else ScanFolder(scan_root)
    clear_verdict(scan)
    surface, downscale = load_surface(scan)
    scene = load_scene(scan.root, downscale=downscale)
    cameras = [Camera(v.viewmat, v.K, v.width, v.height) for v in scene.train]
    infill, infill_source = scan_infill(scan, surface, cameras)
    if len(infill) == 0:
        raise BadInputError(f"{scan.model_dir}: the infill is empty; the model has no inside to mesh or score")
    model = splat_model_of(surface)
    train = train_metrics(scan)
    asset = scan.asset_dir
    files = {name: asset / name for name in ("splat.ply", "infill.ply", "splat.splat", "splat.spz", "splat.glb",
                                               "mesh.ply", "mesh.glb", "metrics.json", "gate.json", "report.html")}
    metrics = evaluate(surface, infill, scene.test)
    metrics["infill_source"] = infill_source
    metrics["train_seconds"] = train.get("report", {}).get("seconds")
    body, body_grid = infill_body(infill.means.numpy(), infill.scales.numpy(), infill_erosion(train, infill_source))
    metrics["infill_volume_m3"] = body_volume(body, body_grid)
    if config.stl:
        files["mesh.stl"] = asset / "mesh.stl"
    mesh = _write_mesh(model, scene, body, body_grid, config, files, metrics)
    metrics["outside_hull_fraction"] = _hull_fraction(model, scene, config)
    # The shipped splats are trimmed of strays (station.export.trim); viewer.html shows them with the mesh.
    shipped, metrics["shipped_splat"] = shipped_splat(model, surface, infill, scene, metrics, config.hull_tolerance)
    for name in ("splat.ply", "splat.splat", "splat.spz", "splat.glb"):
        write_splat(files[name], shipped)
    write_splat(files["infill.ply"], infill_splat(infill))
    metrics["viewer"] = write_viewer(asset / "viewer.html", scan.root.name, files["splat.spz"], files.get("mesh.glb"),
                                     shipped.means.min(axis=0), shipped.means.max(axis=0))
    if config.reference_mesh is not None and mesh is not None:
        if not Path(config.reference_mesh).is_file():
            raise BadInputError(f"{config.reference_mesh}: reference mesh not found")
        truth = trimesh.load_mesh(config.reference_mesh)
        metrics["geometry"] = compare_meshes(mesh, truth, samples=config.truth_samples).to_json()
        metrics["geometry"]["reference"] = str(config.reference_mesh)

    gate = evaluate_gate(metrics, config.gate)
    metrics["export_seconds"] = round(time.perf_counter() - started, 2)
    atomic_write_json(files["metrics.json"], metrics)
    write_gate(files["gate.json"], gate)
    quarantine = asset / "QUARANTINED.txt"
    if gate.passed:
        quarantine.unlink(missing_ok=True)
    else:
        atomic_write_text(quarantine, _quarantine_text(scan, gate))
        files["QUARANTINED.txt"] = quarantine
    panels = render_panels(surface, infill, scene, config.report_views, config.strip_views)
    write_report(files["report.html"], ReportInputs(scan.root.name, metrics, gate, train, panels))
    seconds = time.perf_counter() - started
    scan.mark_done("export", {"pass": gate.passed, "seconds": round(seconds, 2), "summary": gate.summary()})
    return ExportReport(scan.root, gate.passed, gate, metrics, files, seconds)
