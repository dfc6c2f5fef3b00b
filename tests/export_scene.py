"""A tiny 'trained' scan folder for export tests, built in seconds.

The surface model is hand-placed: opaque flat discs on the true surface of a procedural stone,
coloured by its albedo. The photos are that model's own renders, so it plays a perfectly trained
model; the infill is built from it by the NGS infill builder, as training would.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import trimesh

from sim.stone import procedural_stone
from station.export.splat_model import matrix_to_quat
from station.ngs.gaussians import Gaussians, rgb_to_sh
from station.ngs.infill import Camera, InfillConfig, build_infill
from station.ngs.raster import rasterization
from station.process.images_io import srgb_to_linear, write_mask_png, write_png16
from station.process.sfm import Intrinsics
from station.process.transforms import PosedFrame, Transforms, write_transforms
from station.rig_geometry import RigGeometry, camera_to_turntable
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with

SIZE = (160, 120)
ELEVATIONS = (10.0, 35.0, 60.0)
AZIMUTHS = 8
INFILL = InfillConfig(levels=(16, 32), erosion_iters=(2, 2), prune_downscale=1)


def disc_surface(mesh: trimesh.Trimesh, albedo, n: int, opacity: float) -> Gaussians:
    """Flat discs tangent to the surface, degree-1 SH with zero view dependence."""
    points, face = trimesh.sample.sample_surface_even(mesh, n, seed=0)
    quats = []
    for normal in mesh.face_normals[face]:
        x = np.cross(normal, [0.3, 0.5, 0.8])
        x /= np.linalg.norm(x)
        quats.append(matrix_to_quat(np.stack([x, np.cross(normal, x), normal], 1)))
    sigma = 0.6 * np.sqrt(mesh.area / len(points))
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


def build_scan(root: Path, seed: int = 3, n_gaussians: int = 6000) -> ScanFolder:
    """Posed images + masks of an opaque disc model, its infill, train metrics and the true mesh."""
    scan = ScanFolder(root)
    stone = procedural_stone(seed, size_m=0.08)
    rig = RigGeometry().scaled(*SIZE)
    intr = Intrinsics(SIZE[0], SIZE[1], rig.focal_px, rig.focal_px, SIZE[0] / 2, SIZE[1] / 2)
    model = disc_surface(stone.mesh, stone.albedo, n_gaussians, opacity=0.995)
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
    cameras = [Camera(viewmats[k], Ks[k], SIZE[0], SIZE[1]) for k in range(len(c2ws)) if k % 8]
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
