"""Mask benchmark: accuracy against the simulated truth and seconds per mask, ours against OpenCV's GrabCut.

For each stone (procedural dark, pale, speckled and grey looks, and the real meshes in
../shared/data/meshes when present) the simulated rig renders a shot at every `--step`th of the 40
azimuths of all 6 rings, and one empty plate per ring. Each frame is exposed with sensor noise,
written as a DNG and developed by `develop_raw`, as a scan's frames are. Each shot is then masked by:
- ours: `compute_mask` with the default settings;
- ours without the two boundary steps (the plate-colour rule for steep contact shadows, and the
  matting of edge pixels), which is what the masks were before them;
- the peer, OpenCV's GrabCut (5 iterations) on the 8-bit sRGB frame, initialised the usual way with
  a rectangle: the box of our seed hull grown by 10 % on each side.
Scores are against sim_truth's rule (stone covers at least half the pixel): IoU, and the false-stone
and missed-stone pixels, per ring; and the seconds per mask.

Every graph our masks cut is also solved by the max-flow peer, scipy's Dinic, in the same run: the
seconds of each solver on the same graph, and whether both give the same cut.

    python bench/masks.py [--size 320x240] [--step 5] [--stones dark,pale,speckled,grey,meshes]

Prints a table and writes bench/results/masks.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from machine import describe  # noqa: E402
from sim.dng import dng_bytes  # noqa: E402
from sim.rig import make_stone  # noqa: E402
from sim.scene import World, render  # noqa: E402
from sim.sensor import SensorModel  # noqa: E402
from station.capture.plan import default_elevations  # noqa: E402
from station.process.develop import DevelopSettings, develop_raw  # noqa: E402
from station.process import masks, maxflow  # noqa: E402
from station.process.masks import MaskSettings, compute_mask, plate_matched, seed_mask  # noqa: E402
from station.rig_geometry import RigGeometry  # noqa: E402
from station.scanfolder import atomic_write_json  # noqa: E402

SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
EXPOSURE_S = 1 / 30
AZIMUTHS = 40
BEFORE = MaskSettings(matte_boundary=False, max_plate_coloured_stone=-1.0)


def developed(radiance: np.ndarray, seed: list[int]) -> np.ndarray:
    """Linear RGB of a frame exposed, written as a DNG and developed, as the scan pipeline does."""
    sensor = SensorModel()
    with tempfile.NamedTemporaryFile(suffix=".dng") as handle:
        handle.write(dng_bytes(sensor.expose(radiance, EXPOSURE_S, 100, np.random.default_rng(seed)), sensor))
        handle.flush()
        return develop_raw(Path(handle.name), DevelopSettings()).linear


def grabcut_mask(shot: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """OpenCV GrabCut from the box of our seed hull, grown by 10 % a side, on the 8-bit sRGB frame."""
    settings = MaskSettings()
    seed = seed_mask(shot, plate_matched(shot, plate, settings), settings)
    h, w = seed.shape
    if not seed.any():
        return seed
    ys, xs = np.nonzero(seed)
    my, mx = int(0.1 * (ys.max() - ys.min() + 1)) + 1, int(0.1 * (xs.max() - xs.min() + 1)) + 1
    x0, y0 = max(0, xs.min() - mx), max(0, ys.min() - my)
    x1, y1 = min(w - 1, xs.max() + mx), min(h - 1, ys.max() + my)
    srgb = np.clip(shot / np.percentile(plate, 99.5), 0.0, 1.0) ** (1 / 2.2)
    image = np.ascontiguousarray((srgb[..., ::-1] * 255).astype(np.uint8))
    labels = np.zeros((h, w), np.uint8)
    background_model, foreground_model = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(image, labels, (int(x0), int(y0), int(x1 - x0), int(y1 - y0)),
                background_model, foreground_model, 5, cv2.GC_INIT_WITH_RECT)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def timed_cuts(mask_fn) -> list[dict]:
    """Runs `mask_fn()` again, apart from the timed run (the graphs' copies would cost it time), and solves
    each graph its cut builds by ours and by the peer: per graph, the node count, each solver's seconds
    and whether their cuts agree."""
    graphs = []
    building = masks._cut_graph

    def recorded(*args):
        graph = building(*args)
        graphs.append(tuple(a.copy() for a in graph))
        return graph

    with mock.patch.object(masks, "_cut_graph", recorded):
        mask_fn()
    rows = []
    for first, head, sister, capacity, terminal in graphs:
        residual, left = capacity.copy(), terminal.copy()
        started = time.perf_counter()
        maxflow.max_flow(first, head, sister, residual, left)
        ours = maxflow.source_side(first, head, residual, left)
        middle = time.perf_counter()
        _, peer = maxflow.reference_cut(first, head, capacity, terminal)
        rows.append({"nodes": int(terminal.size), "ours_s": middle - started,
                     "scipy_dinic_s": time.perf_counter() - middle, "same_cut": bool(np.array_equal(ours, peer))})
    return rows


def stone_specs(names: str) -> list[str]:
    """`make_stone` specs for a comma list of procedural looks (seed 3, or 'look:seed') and 'meshes' (the real
    meshes, when present)."""
    specs = []
    for name in names.split(","):
        if name == "meshes":
            specs += [str(p) for p in sorted(SHARED_MESHES.glob("*.ply"))] if SHARED_MESHES.is_dir() else []
        else:
            specs.append(name if ":" in name else f"{name}:3")
    return specs


def score(mask: np.ndarray, truth: np.ndarray) -> dict:
    return {"iou": float((mask & truth).sum() / max((mask | truth).sum(), 1)),
            "false_stone_px": int((mask & ~truth).sum()), "missed_stone_px": int((~mask & truth).sum())}


def stone_rows(spec: str, size: tuple[int, int], step: int) -> tuple[list[dict], list[dict]]:
    world = World(make_stone(spec), rig=RigGeometry().scaled(*size))
    methods = {
        "ours": lambda shot, plate: compute_mask(shot, plate),
        "ours_before_boundary_steps": lambda shot, plate: compute_mask(shot, plate, BEFORE),
        "grabcut": grabcut_mask,
    }
    rows, cuts = [], []
    for ring, elevation in enumerate(default_elevations(6)):
        plate = developed(render(world, elevation, 0.0, stone_present=False).radiance, [ring, AZIMUTHS])
        for a in range(0, AZIMUTHS, step):
            frame = render(world, elevation, 360.0 * a / AZIMUTHS, stone_present=True)
            shot = developed(frame.radiance, [ring, a])
            for method, fn in methods.items():
                started = time.perf_counter()
                mask = fn(shot, plate)
                seconds = time.perf_counter() - started
                rows.append({"stone": world.stone.name, "ring": ring, "elevation_deg": elevation, "azimuth_index": a,
                             "method": method, "seconds": seconds, **score(mask, frame.mask)})
            cuts += timed_cuts(lambda: compute_mask(shot, plate))
    return rows, cuts


def summary(rows: list[dict]) -> list[dict]:
    """Per stone, method and ring: mean and min IoU, mean false/missed pixels, mean seconds."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["stone"], row["method"], row["ring"]), []).append(row)
    out = []
    for (stone, method, ring), group in groups.items():
        ious = [g["iou"] for g in group]
        out.append({"stone": stone, "method": method, "ring": ring, "elevation_deg": group[0]["elevation_deg"],
                    "views": len(group), "iou_mean": round(float(np.mean(ious)), 4),
                    "iou_min": round(float(np.min(ious)), 4),
                    "false_stone_px_mean": round(float(np.mean([g["false_stone_px"] for g in group])), 1),
                    "missed_stone_px_mean": round(float(np.mean([g["missed_stone_px"] for g in group])), 1),
                    "seconds_mean": round(float(np.mean([g["seconds"] for g in group])), 4)})
    return out


def max_flow_summary(cuts: list[dict]) -> dict:
    ours = float(np.mean([c["ours_s"] for c in cuts]))
    peer = float(np.mean([c["scipy_dinic_s"] for c in cuts]))
    return {"graphs": len(cuts), "nodes_mean": round(float(np.mean([c["nodes"] for c in cuts])), 1),
            "ours_ms": round(1e3 * ours, 2), "scipy_dinic_ms": round(1e3 * peer, 2),
            "ours_over_scipy": round(ours / peer, 3), "same_cut": sum(c["same_cut"] for c in cuts)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="320x240", help="simulated camera size WxH (the scan default)")
    parser.add_argument("--step", type=int, default=5, help="mask every step-th of the 40 azimuths per ring")
    parser.add_argument("--stones", default="dark,pale,speckled,grey,meshes",
                        help="procedural looks, and 'meshes' for the real meshes in ../shared/data/meshes")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "masks.json")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    rows, cuts = [], []
    for spec in stone_specs(args.stones):
        stone, stone_cuts = stone_rows(spec, size, args.step)
        rows += stone
        cuts += stone_cuts
    table_rows = summary(rows)

    table = Table(title=f"Masks at {size[0]}x{size[1]}: mean IoU against sim truth per ring, worst view, pixels per view")
    for column in ("stone", "method", *[f"e{r}" for r in range(6)], "min", "false px", "missed px", "s/mask"):
        table.add_column(column)
    by_key: dict[tuple, list[dict]] = {}
    for row in table_rows:
        by_key.setdefault((row["stone"], row["method"]), []).append(row)
    for (stone, method), group in by_key.items():
        group.sort(key=lambda r: r["ring"])
        table.add_row(stone, method, *[f"{g['iou_mean']:.4f}" for g in group], f"{min(g['iou_min'] for g in group):.4f}",
                      f"{np.mean([g['false_stone_px_mean'] for g in group]):.0f}",
                      f"{np.mean([g['missed_stone_px_mean'] for g in group]):.0f}",
                      f"{np.mean([g['seconds_mean'] for g in group]):.3f}")
    Console(width=180).print(table)
    ours = np.mean([r["seconds"] for r in rows if r["method"] == "ours"])
    peer = np.mean([r["seconds"] for r in rows if r["method"] == "grabcut"])
    record = {
        "machine": describe(),
        "size": list(size), "views_per_ring": AZIMUTHS // args.step,
        "seconds_per_mask": {"ours": round(float(ours), 4), "grabcut": round(float(peer), 4),
                             "ours_over_grabcut": round(float(ours / peer), 3)},
        "max_flow": max_flow_summary(cuts),
        "summary": table_rows, "rows": rows,
    }
    atomic_write_json(args.out, record)
    print(f"ours {ours:.3f} s/mask, GrabCut {peer:.3f} s/mask (ratio {ours / peer:.2f}); wrote {args.out}")
    flows = record["max_flow"]
    print(f"max-flow on {flows['graphs']} cut graphs of {flows['nodes_mean']:.0f} nodes: ours {flows['ours_ms']} ms, "
          f"scipy's Dinic {flows['scipy_dinic_ms']} ms (ratio {flows['ours_over_scipy']}); "
          f"same cut on {flows['same_cut']} of {flows['graphs']}")


if __name__ == "__main__":
    main()
