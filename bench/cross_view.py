"""Masks of whole simulated scans, per ring: the first cut against the cut again across rings.

For each stone the simulated rig shoots a full scan (6 rings x 40 by default, 320x240, as
`station scan --sim`), then the process stage develops and masks it (`develop_scan`), poses it on
the scan's own rig (`pose_scan`), and cuts the masks again with the other rings' silhouettes
(`refine_masks_across_rings`). The masks are scored against sim_truth per ring after the first cut
and after the re-cut, in the same run, with the seconds each step took. With `--training-width`
(the demo's setup: `--sensor 640x480 --training-width 320`) the masks are cut at the sensor's size
and averaged down, and they are scored against the truth rendered at the training size (16
samples a pixel).

    python bench/cross_view.py [--stones pale,speckled,dark,grey,meshes] [--azimuths 40] [--work DIR]
                               [--sensor 320x240] [--training-width W]

Prints a table and writes bench/results/masks_across_rings.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from machine import describe  # noqa: E402
from masks import score, stone_specs  # noqa: E402  (bench/masks.py)
from sim.rig import make_stone  # noqa: E402
from sim.truth import mask_path_for, true_masks_at  # noqa: E402
from station.cli_scan import run_sim_scan  # noqa: E402
from station.process.cross_view import refine_masks_across_rings  # noqa: E402
from station.process.develop_stage import DevelopReport, ProcessSettings, develop_scan  # noqa: E402
from station.process.images_io import read_mask_png  # noqa: E402
from station.process.poses import PoseSettings, pose_scan  # noqa: E402
from station.process.stage import station_rig_model  # noqa: E402
from station.scanfolder import ScanFolder, atomic_write_json  # noqa: E402



def ring_scores(scan: ScanFolder, elevation_of: dict[str, float], truth: dict[str, np.ndarray]) -> dict[float, dict]:
    """Per ring: mean and min IoU of masks/ against `truth`, mean false and missed stone pixels."""
    rows: dict[float, list[dict]] = {}
    for file, elevation in elevation_of.items():
        mask = read_mask_png(scan.masks_dir / f"{Path(file).stem}.png")
        rows.setdefault(elevation, []).append(score(mask, truth[file]))
    return {e: {"iou_mean": round(float(np.mean([r["iou"] for r in v])), 4),
                "iou_min": round(float(np.min([r["iou"] for r in v])), 4),
                "false_stone_px_mean": round(float(np.mean([r["false_stone_px"] for r in v])), 1),
                "missed_stone_px_mean": round(float(np.mean([r["missed_stone_px"] for r in v])), 1)}
            for e, v in sorted(rows.items())}


def truth_masks(scan: ScanFolder, spec: str, developed: DevelopReport, training_width: int | None) -> dict[str, np.ndarray]:
    """The true mask of every masked shot: sim_truth's, or rendered at the training size when there is one."""
    shots = [f.file for f in developed.frames if f.kind == "shot" and f.mask_area_fraction is not None]
    if training_width is None:
        return {file: read_mask_png(mask_path_for(scan.root, file)) for file in shots}
    return true_masks_at(scan.root, make_stone(spec), training_width, shots)


def stone_record(spec: str, root: Path, azimuths: int, sensor: tuple[int, int], training_width: int | None) -> dict:
    started = time.perf_counter()
    run_sim_scan(root, spec, 6, azimuths, sensor, 0.01, lambda done, total, what: None)
    scan = ScanFolder(root)
    seconds = {"scan": time.perf_counter() - started}
    settings = ProcessSettings(training_width=training_width)
    started = time.perf_counter()
    developed = develop_scan(scan, settings)
    seconds["develop_and_first_cut"] = time.perf_counter() - started
    elevation_of = {f.file: f.elevation_deg for f in developed.frames if f.kind == "shot" and f.mask_area_fraction is not None}
    truth = truth_masks(scan, spec, developed, training_width)
    first = ring_scores(scan, elevation_of, truth)
    started = time.perf_counter()
    pose_scan(scan, PoseSettings(), station_rig_model(scan, None))
    seconds["poses"] = time.perf_counter() - started
    started = time.perf_counter()
    across = refine_masks_across_rings(scan, developed, settings)
    seconds["across_rings"] = time.perf_counter() - started
    again = ring_scores(scan, elevation_of, truth)
    return {"stone": scan.read_scan_json().get("stone_id", spec), "spec": spec,
            "seconds": {k: round(v, 1) for k, v in seconds.items()},
            "recut_views": {str(r["elevation_deg"]): len(r.get("recut", [])) for r in across.get("rings", [])},
            "rings": [{"elevation_deg": e, "first_cut": first[e], "across_rings": again[e]} for e in first]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stones", default="pale,speckled,dark,grey,meshes",
                        help="procedural looks, and 'meshes' for the real meshes in ../shared/data/meshes")
    parser.add_argument("--azimuths", type=int, default=40)
    parser.add_argument("--work", type=Path, default=None, help="keep the scans here (default: a temporary folder)")
    parser.add_argument("--sensor", default="320x240", help="simulated sensor size WxH")
    parser.add_argument("--training-width", type=int, default=None, help="area-average the masks down to this width")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "masks_across_rings.json")
    args = parser.parse_args()
    sensor = tuple(int(v) for v in args.sensor.split("x"))
    with tempfile.TemporaryDirectory() as scratch:
        work = args.work or Path(scratch)
        records = [stone_record(spec, work / f"scan-{i}", args.azimuths, sensor, args.training_width)
                   for i, spec in enumerate(stone_specs(args.stones))]

    scored = f"{sensor[0]}x{sensor[1]}" + (f" averaged to {args.training_width} wide" if args.training_width else "")
    table = Table(title=f"Mask IoU per ring against sim truth, {scored}, 6 x {args.azimuths} views: "
                        "first cut -> cut again across rings (views re-cut)")
    for column in ("stone", *[f"e{r}" for r in range(6)], "across-rings s"):
        table.add_column(column)
    for record in records:
        cells = []
        for ring in record["rings"]:
            recut = record["recut_views"].get(str(ring["elevation_deg"]), 0)
            cells.append(f"{ring['first_cut']['iou_mean']:.4f} -> {ring['across_rings']['iou_mean']:.4f} ({recut})")
        table.add_row(record["stone"], *cells, f"{record['seconds']['across_rings']:.0f}")
    Console(width=200).print(table)
    atomic_write_json(args.out, {"machine": describe(),
                                 "sensor": list(sensor), "training_width": args.training_width,
                                 "azimuths": args.azimuths, "stones": records})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
