"""Mesh benchmark: the opacity level set against the TSDF of median depth, time against error.

Both meshers run on the same trained scan in the same run, with the same grid and the same infill
body, and are scored against the scan's true mesh (sim_truth/mesh.ply): volume error, Chamfer-L1
(point-to-mesh) as a share of the bounding-box diagonal, F-score at 1 % of the diagonal. The TSDF
is the peer; the table gives the level set's time and Chamfer as ratios to it.

    python bench/mesh.py [--scan demo-out/scan] [--repeats 3]

The scan must be trained (`./dev demo` leaves one in demo-out/scan). Prints a table and writes
bench/results/mesh.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import trimesh
from rich.console import Console
from rich.table import Table

from station.export.geometry_metrics import compare_meshes
from station.export.infill_occupancy import infill_body
from station.export.stage import ExportConfig, infill_erosion, mesh_splat, splat_model_of, train_metrics
from station.ngs.dataset import load_scene
from station.ngs.infill import Camera
from station.ngs.sos import load_surface, scan_infill
from station.scanfolder import ScanFolder, atomic_write_json
from machine import describe

RESULTS = Path(__file__).parent / "results" / "mesh.json"
DEFAULT_SCAN = Path(__file__).resolve().parents[1] / "demo-out" / "scan"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scan", type=Path, default=DEFAULT_SCAN)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    scan = ScanFolder(args.scan)
    truth_path = scan.sim_truth_dir / "mesh.ply"
    if not (scan.model_dir / "surface.pt").is_file() or not truth_path.is_file():
        sys.exit(f"{args.scan}: needs a trained simulated scan (model/surface.pt and sim_truth/mesh.ply); "
                 "run ./dev demo first")

    surface, downscale = load_surface(scan)
    scene = load_scene(scan.root, downscale=downscale)
    cameras = [Camera(v.viewmat, v.K, v.width, v.height) for v in scene.train]
    infill, source = scan_infill(scan, surface, cameras)
    body, body_grid = infill_body(infill.means.numpy(), infill.scales.numpy(),
                                  infill_erosion(train_metrics(scan), source))
    model = splat_model_of(surface)
    truth = trimesh.load_mesh(truth_path)
    base = ExportConfig()
    rows = {}
    for method in ("tsdf", "opacity"):
        config = replace(base, mesh=replace(base.mesh, surface=method))
        times = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            mesh, grid = mesh_splat(model, scene, body, body_grid, config)
            times.append(time.perf_counter() - started)
        errors = compare_meshes(mesh, truth, samples=base.truth_samples).to_json()
        rows[method] = {"seconds": min(times), "voxel_m": grid.voxel_size, "faces": len(mesh.faces),
                        "watertight": bool(mesh.is_watertight), **errors}

    peer = rows["tsdf"]
    result = {
        "benchmark": "mesh",
        "machine": describe(),
        "scan": str(args.scan),
        "peer": "TSDF of median-depth maps (mesh.surface = 'tsdf'), same grid and infill, same run",
        "methods": rows,
        "opacity_time_ratio_to_tsdf": rows["opacity"]["seconds"] / peer["seconds"],
        "opacity_chamfer_ratio_to_tsdf": rows["opacity"]["chamfer_fraction_of_diagonal"] / peer["chamfer_fraction_of_diagonal"],
    }
    atomic_write_json(args.out, result)

    table = Table(title=f"Meshing {args.scan} (best of {args.repeats})")
    for column in ("method", "seconds", "volume error", "Chamfer / diag", "F-score@1%", "watertight"):
        table.add_column(column, justify="left" if column == "method" else "right")
    for name, r in rows.items():
        table.add_row(name, f"{r['seconds']:.2f}", f"{r['volume_rel_error']:+.1%}",
                      f"{r['chamfer_fraction_of_diagonal']:.2%}", f"{r['fscore']:.3f}", str(r["watertight"]))
    Console().print(table)
    print(f"opacity / tsdf: time x{result['opacity_time_ratio_to_tsdf']:.2f}, "
          f"Chamfer x{result['opacity_chamfer_ratio_to_tsdf']:.2f}; wrote {args.out}")


if __name__ == "__main__":
    main()
