"""Process benchmark: develop speed against rawpy, posing error against views, training views against the truth.

(a) Develop: seconds per megapixel of `develop_raw` (LibRaw AHD, linear 16-bit, colour matrix, stats)
    against rawpy's default `postprocess()` (AHD, 8-bit sRGB, auto-bright) on the same file, in the
    same run: simulated DNGs of several sizes and the real raws in ../shared/data/raw when present.
    Also the seconds per image of the masks (no peer: nothing else here masks against a plate).
(b) Posing: one simulated 6 x 40 scan of a speckled stone (rendered, exposed, DNG-encoded, developed
    and masked by `develop_scan`), posed on subsets of 40, 120 and 240 views by the rig path (rig
    poses + triangulation + prior-guided cross-check mapping) and by the pure-SfM fallback (bounded by
    COLMAP's max runtime). Errors are against sim_truth/cameras.json: rotation in degrees and camera
    centre as % of the orbit radius; rig-path poses are compared as they are (rig frame), SfM poses
    after a similarity alignment to the truth.

    python bench/process.py [--size 480x360] [--views 40,120,240] [--sfm-views 40,120,240] [--repeats 3]
(c) Image fidelity (`--fidelity`): simulated scans (640x480 by default, training images at 320) developed
    and masked by `develop_scan`; per ring, the training views scored against the truth images
    (sim/fidelity.py: PSNR on the stone, in the silhouette band and on the plate, dE00 on the stone,
    false-colour pixels on the silhouette, mask IoU), beside the develop and matte seconds per view.

    python bench/process.py --fidelity [--stones 0,pale:3] [--rings 6] [--azimuths 40] [--fidelity-size 640x480]

The posing scan is 480x360 by default, not the 640x480 the posing tests use: at 640x480, rendering
and developing the 246 frames alone took 7 minutes on the shared 2-core bench machine, and posing
240 views grows with the square of the view count (exhaustive matching), past a 15-minute budget.

Prints tables and writes bench/results/process.json (process_fidelity.json with --fidelity).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import rawpy
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from machine import describe  # noqa: E402
from bench.masks import developed  # noqa: E402
from sim.dng import dng_bytes  # noqa: E402
from sim.fidelity import ring_summary, scan_fidelity  # noqa: E402
from sim.rig import direct_scan, make_stone  # noqa: E402
from sim.scene import World, render  # noqa: E402
from sim.sensor import SensorModel  # noqa: E402
from sim.stone import procedural_stone  # noqa: E402
from station.capture.plan import default_elevations  # noqa: E402
from station.process.develop import DevelopSettings, develop_raw  # noqa: E402
from station.process.develop_stage import ProcessSettings, develop_scan  # noqa: E402
from station.process.masks import compute_mask  # noqa: E402
from station.process.poses import PoseSettings, pose_scan  # noqa: E402
from station.process.rig_model import RigModel, rotation_angle_deg, umeyama  # noqa: E402
from station.process.sfm import SfmSettings  # noqa: E402
from station.process.transforms import read_transforms  # noqa: E402
from station.rig_geometry import RigGeometry  # noqa: E402
from station.scanfolder import ScanFolder, atomic_write_json  # noqa: E402

SHARED_RAW = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw"
RAW_SUFFIXES = (".dng", ".crw", ".cr2", ".nef", ".arw", ".kdc", ".orf", ".raf", ".rw2")
AZIMUTHS = 40
EXPOSURE_S = 1 / 30
THREADS = 2  # SfmSettings.num_threads; LibRaw's AHD runs on one thread


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return float(np.median(times))


def _sim_dng(path: Path, width: int, height: int) -> None:
    """A DNG of a rendered stone, resized to the sensor size (develop cost does not depend on content)."""
    world = World(procedural_stone(3, look="speckled"), rig=RigGeometry().scaled(640, 480))
    radiance = cv2.resize(render(world, 40.0, 0.0).radiance, (width, height), interpolation=cv2.INTER_LINEAR)
    sensor = SensorModel()
    path.write_bytes(dng_bytes(sensor.expose(radiance, EXPOSURE_S, 100, np.random.default_rng(0)), sensor))


def develop_rows(work: Path, sizes: list[tuple[int, int]], repeats: int) -> list[dict]:
    """Our develop and rawpy's default postprocess on each raw, timed back to back, file open included."""
    sources = []
    for width, height in sizes:
        path = work / f"sim_{width}x{height}.dng"
        _sim_dng(path, width, height)
        sources.append(("simulated DNG", path))
    if SHARED_RAW.is_dir():
        sources += [("real raw", p) for p in sorted(SHARED_RAW.iterdir()) if p.suffix.lower() in RAW_SUFFIXES]

    def peer(path: Path) -> None:
        with rawpy.imread(str(path)) as raw:
            raw.postprocess()

    rows = []
    for kind, path in sources:
        with rawpy.imread(str(path)) as raw:
            height, width = raw.raw_image_visible.shape
        megapixels = width * height / 1e6
        ours = _median_seconds(lambda: develop_raw(path, DevelopSettings()), repeats)
        theirs = _median_seconds(lambda: peer(path), repeats)
        rows.append({
            "source": path.name, "kind": kind, "width": width, "height": height, "megapixels": round(megapixels, 3),
            "ours_s": round(ours, 4), "ours_s_per_mp": round(ours / megapixels, 4),
            "rawpy_default_s": round(theirs, 4), "rawpy_default_s_per_mp": round(theirs / megapixels, 4),
            "ours_over_rawpy": round(ours / theirs, 3),
        })
    return rows


def mask_rows(sizes: list[tuple[int, int]], repeats: int) -> list[dict]:
    """Seconds per image of `compute_mask` on developed shot/plate pairs (frames over 1280 px are masked
    at 1280 px and the mask resized back, see MaskSettings.max_working_side)."""
    world = World(procedural_stone(3, look="speckled"), rig=RigGeometry().scaled(640, 480))
    shot, plate = (render(world, 45.0, 90.0, stone_present=p).radiance for p in (True, False))
    rows = []
    for width, height in sizes:
        frames = [developed(cv2.resize(radiance, (width, height), interpolation=cv2.INTER_LINEAR), [noise_seed])
                  for noise_seed, radiance in enumerate((shot, plate))]  # each frame its own noise, as on a camera
        seconds = _median_seconds(lambda: compute_mask(*frames), repeats)
        rows.append({"width": width, "height": height, "seconds": round(seconds, 3)})
    return rows


def _frame_name(e_index: int, a_index: int) -> str:
    return f"e{e_index}_a{a_index:03d}"


def make_scan(root: Path, rig: RigGeometry, elevations: tuple[float, ...], seed: int = 11) -> ScanFolder:
    """A 6 x 40 scan of a 9 cm speckled stone as capture leaves it (sim.rig.direct_scan)."""
    stone = procedural_stone(seed, size_m=0.09, look="speckled")
    return direct_scan(root, stone, rig, elevations, AZIMUTHS, exposure_s=EXPOSURE_S, seed=seed)


def fidelity_rows(work: Path, stones: list[str], size: tuple[int, int], training_width: int, rings: int,
                  azimuths: int) -> list[dict]:
    """Per stone and ring: the training views against the truth, and the develop and matte seconds per view."""
    rows = []
    for spec in stones:
        root = work / f"fidelity_{Path(spec).stem.replace(':', '_')}_{size[0]}x{size[1]}_{rings}x{azimuths}"
        if (root / "manifest.jsonl").is_file():  # kept from an earlier run (--keep-scans): developed again
            scan = ScanFolder(root)
        else:
            scan = direct_scan(root, make_stone(spec), RigGeometry().scaled(*size), default_elevations(rings),
                               azimuths, exposure_s=EXPOSURE_S, seed=5)
        report = develop_scan(scan, ProcessSettings(training_width=training_width))
        shots = len([f for f in report.frames if f.kind == "shot"])
        for elevation, views in scan_fidelity(scan).items():
            rows.append({"stone": spec, "elevation_deg": elevation, **ring_summary(views),
                         "develop_s_per_view": round((report.seconds - report.matte_seconds) / shots, 3),
                         "matte_s_per_view": round(report.matte_seconds / shots, 3)})
        print(f"  scored {spec}: develop+matte {report.seconds:.0f} s", flush=True)
    return rows


def fidelity_main(args: argparse.Namespace, console: Console) -> None:
    started, load_before = time.perf_counter(), os.getloadavg()
    size = tuple(int(v) for v in args.fidelity_size.split("x"))
    with tempfile.TemporaryDirectory(prefix="bench-fidelity-") as tmp:
        work = args.keep_scans or Path(tmp)
        rows = fidelity_rows(work, args.stones.split(","), size, args.training_width, args.rings, args.azimuths)
    table = Table(title=f"training views against the truth: {size[0]}x{size[1]} cut, trained at {args.training_width}")
    for column in ("stone", "ring deg", "views", "false colour /view (max)", "PSNR stone", "PSNR band", "PSNR plate",
                   "dE00 stone", "IoU", "develop s/view", "matte s/view"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["stone"], f"{r['elevation_deg']:g}", str(r["views"]),
                      f"{r['false_colour_per_view']:.2f} ({r['false_colour_max']})", f"{r['psnr_stone_db']:.2f}",
                      f"{r['psnr_band_db']:.2f}", f"{r['psnr_plate_db']:.2f}", f"{r['delta_e00_stone']:.3f}",
                      f"{r['iou_mean']:.4f}", f"{r['develop_s_per_view']:.3f}", f"{r['matte_s_per_view']:.3f}")
    console.print(table)
    result = {"benchmark": "process_fidelity", "label": args.label,
              "machine": {**describe(), "load_average_before": load_before,
                          "load_average_after": os.getloadavg(),
                          "note": "shared machine: other jobs ran alongside, so times are inflated and noisy"},
              "scan": {"size": list(size), "training_width": args.training_width, "rings": args.rings,
                       "azimuths": args.azimuths, "elevations_deg": list(default_elevations(args.rings))},
              "metrics": "sim/fidelity.py", "rows": rows, "total_s": round(time.perf_counter() - started, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    console.print(f"wrote {args.out} in {result['total_s']:.0f} s")


# views -> (elevation ring indices into the 6 planned rings, azimuths per ring)
SUBSETS = {40: ((1, 4), 20), 120: ((0, 2, 4), 40), 240: ((0, 1, 2, 3, 4, 5), 40)}


def view_subset(count: int) -> list[tuple[int, int]]:
    """(elevation index, azimuth index) of a `count`-view subset of the 6 x 40 scan."""
    rings, per_ring = SUBSETS[count]
    step = AZIMUTHS // per_ring
    return [(e, k * step) for e in rings for k in range(per_ring)]


def subset_scan(full: ScanFolder, root: Path, views: list[tuple[int, int]]) -> ScanFolder:
    """A developed scan folder holding only `views`: images, masks, manifest and scan.json."""
    scan = ScanFolder(root)
    scan.images_dir.mkdir(parents=True)
    scan.masks_dir.mkdir()
    keep = {_frame_name(e, a) for e, a in views}
    entries = [e for e in full.read_manifest() if e.kind == "shot" and Path(e.file).stem in keep]
    for entry in entries:
        stem = Path(entry.file).stem
        shutil.copy(full.images_dir / f"{stem}.png", scan.images_dir / f"{stem}.png")
        shutil.copy(full.masks_dir / f"{stem}.png", scan.masks_dir / f"{stem}.png")
    scan.write_manifest(entries)
    record = full.read_scan_json()
    record["plan"]["elevations_deg"] = sorted({e.elevation_deg for e in entries})
    atomic_write_json(scan.scan_json, record)
    return scan


def pose_errors(scan: ScanFolder, truth: dict[str, np.ndarray], radius: float, align: bool) -> dict:
    """Rotation (deg) and centre (% of orbit radius) errors of the written poses against the truth."""
    posed = {Path(f.file_path).stem: f.c2w for f in read_transforms(scan).frames}
    names = sorted(posed)
    if align:
        s, r, t = umeyama(np.array([posed[n][:3, 3] for n in names]), np.array([truth[n][:3, 3] for n in names]))
    else:
        s, r, t = 1.0, np.eye(3), np.zeros(3)
    rot = [rotation_angle_deg(r @ posed[n][:3, :3], truth[n][:3, :3]) for n in names]
    ctr = [100 * np.linalg.norm(s * r @ posed[n][:3, 3] + t - truth[n][:3, 3]) / radius for n in names]
    return {"rotation_median_deg": round(float(np.median(rot)), 4), "rotation_max_deg": round(float(max(rot)), 4),
            "centre_median_pct": round(float(np.median(ctr)), 4), "centre_max_pct": round(float(max(ctr)), 4)}


def posing_rows(work: Path, rig: RigGeometry, view_counts: list[int], sfm_counts: list[int],
                sfm_max_runtime_s: float) -> tuple[list[dict], dict]:
    elevations = default_elevations(6)
    started = time.perf_counter()
    full = make_scan(work / "full", rig, elevations)
    made = time.perf_counter() - started
    started = time.perf_counter()
    developed = develop_scan(full)
    develop_s = time.perf_counter() - started
    cameras = json.loads((full.sim_truth_dir / "cameras.json").read_text())["frames"]
    truth = {Path(c["file"]).stem: np.array(c["camera_to_world"]) for c in cameras}
    radius = rig.orbit_radius_m
    rows = []
    for count in view_counts:
        views = view_subset(count)
        for method in ("rig", "sfm"):
            if method == "sfm" and count not in sfm_counts:
                continue
            scan = subset_scan(full, work / f"{method}_{count}", views)
            model = RigModel.nominal(rig, sorted({elevations[e] for e, _ in views})) if method == "rig" else None
            settings = PoseSettings(sfm=SfmSettings(num_threads=THREADS, max_runtime_s=sfm_max_runtime_s))
            started = time.perf_counter()
            report = pose_scan(scan, settings, model)
            seconds = time.perf_counter() - started
            row = {"views": count, "method": method, "seconds": round(seconds, 1),
                   "registered": len(report.registered), "points": report.points, "init_cloud": report.init_cloud,
                   "reprojection_error_px": round(report.reprojection_error_px, 3),
                   **pose_errors(scan, truth, radius, align=method == "sfm")}
            if method == "rig":
                rings = report.cross_check["ring_offsets"].values()  # shifts are fractions of the model's radius
                to_pct = 100 * model.orbit_radius() / radius
                row["cross_check"] = {"ring_rotation_max_deg": round(max(r["rotation_deg"] for r in rings), 4),
                                      "ring_centre_max_pct": round(to_pct * max(r["centre_fraction"] for r in rings), 4),
                                      "epipolar_px_median": round(float(np.median([r["epipolar_px_rig"]
                                                                                   for r in rings])), 4),
                                      "drift_flagged_elevations": report.cross_check["drifted_elevations"]}
            rows.append(row)
            print(f"  posed {count} views by {method}: {seconds:.1f} s", flush=True)
    scan_info = {"stone": "procedural speckled, seed 11, 9 cm", "size": [rig.width, rig.height],
                 "elevations_deg": list(elevations), "azimuths": AZIMUTHS, "orbit_radius_m": round(radius, 4),
                 "render_and_encode_s": round(made, 1), "develop_and_mask_s": round(develop_s, 1),
                 "develop_and_mask_s_per_image": round(develop_s / len(developed.frames), 3)}
    return rows, scan_info


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="480x360", help="simulated camera size for the posing scan")
    parser.add_argument("--views", default="40,120,240", help=f"any of {sorted(SUBSETS)}")
    parser.add_argument("--sfm-views", default="40,120,240", help="view counts also posed by pure SfM")
    parser.add_argument("--sfm-max-runtime", type=float, default=180.0, help="COLMAP mapping bound per run (s)")
    parser.add_argument("--develop-sizes", default="640x480,2000x1500,4000x3000")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fidelity", action="store_true", help="only (c): the training views against the truth")
    parser.add_argument("--stones", default="0,pale:3,dark:7,speckled:11", help="stone specs (sim.rig.make_stone)")
    parser.add_argument("--fidelity-size", default="640x480")
    parser.add_argument("--training-width", type=int, default=320)
    parser.add_argument("--rings", type=int, default=6)
    parser.add_argument("--azimuths", type=int, default=40)
    parser.add_argument("--label", default="", help="what this run measured, kept in the JSON")
    parser.add_argument("--keep-scans", type=Path, default=None, help="make the fidelity scans here and reuse them")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    console = Console(width=140)
    if args.fidelity:
        args.out = args.out or Path(__file__).parent / "results" / "process_fidelity.json"
        fidelity_main(args, console)
        return
    args.out = args.out or Path(__file__).parent / "results" / "process.json"
    width, height = (int(v) for v in args.size.split("x"))
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.develop_sizes.split(",")]
    started, load_before = time.perf_counter(), os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-process-") as tmp:
        work = Path(tmp)
        develop = develop_rows(work, sizes, args.repeats)
        table = Table(title="develop: ours (linear AHD + matrix) vs rawpy default postprocess(), same files")
        for column in ("source", "MP", "ours s", "ours s/MP", "rawpy s", "rawpy s/MP", "ours/rawpy"):
            table.add_column(column, overflow="fold")
        for r in develop:
            table.add_row(r["source"], f"{r['megapixels']:.2f}", f"{r['ours_s']:.3f}", f"{r['ours_s_per_mp']:.3f}",
                          f"{r['rawpy_default_s']:.3f}", f"{r['rawpy_default_s_per_mp']:.3f}",
                          f"{r['ours_over_rawpy']:.2f}")
        console.print(table)
        masks = mask_rows([(640, 480), (1280, 960), (2560, 1920)], args.repeats)
        console.print("masks (speckled stone, graph cut): " + ", ".join(
            f"{r['width']}x{r['height']} {r['seconds']:.2f} s" for r in masks))
        rig = RigGeometry().scaled(width, height)
        posing, scan_info = posing_rows(work, rig, [int(v) for v in args.views.split(",")],
                                        [int(v) for v in args.sfm_views.split(",")], args.sfm_max_runtime)
    table = Table(title=f"posing a simulated speckled stone at {width}x{height} against sim truth")
    for column in ("views", "method", "s", "registered", "points", "rot med/max deg", "centre med/max %",
                   "cross-check ring turn/shift max"):
        table.add_column(column, overflow="fold")
    for r in posing:
        check = r.get("cross_check")
        table.add_row(str(r["views"]), r["method"], f"{r['seconds']:.1f}", str(r["registered"]), str(r["points"]),
                      f"{r['rotation_median_deg']:.3f} / {r['rotation_max_deg']:.3f}",
                      f"{r['centre_median_pct']:.3f} / {r['centre_max_pct']:.3f}",
                      "-" if check is None else f"{check['ring_rotation_max_deg']:.3f} deg, "
                                                f"{check['ring_centre_max_pct']:.3f} %, drift {check['drift_flagged_elevations']}")
    console.print(table)
    result = {
        "benchmark": "process",
        "machine": {**describe(), "load_average_before": load_before, "load_average_after": os.getloadavg(),
                    "note": "shared machine: other jobs ran alongside, so absolute times are inflated"},
        "threads": {"colmap": THREADS, "libraw": 1},
        "versions": {"rawpy": rawpy.__version__, "libraw": ".".join(map(str, rawpy.libraw_version)),
                     "pycolmap": __import__("pycolmap").__version__, "opencv": cv2.__version__},
        "develop": {"repeats": args.repeats, "peer": "rawpy.RawPy.postprocess() with default arguments "
                    "(AHD, 8-bit sRGB, gamma, auto-bright, daylight WB), file open included on both sides",
                    "rows": develop},
        "masks": {"repeats": args.repeats, "rows": masks},
        "posing": {"scan": scan_info, "subsets": {str(k): {"rings": list(v[0]), "azimuths_per_ring": v[1]}
                                                  for k, v in SUBSETS.items()},
                   "resolution_note": "480x360 by default (640x480 did not fit in ~15 min on this machine); "
                                      "fewer SIFT features there than at 640x480",
                   "sfm_max_runtime_s": args.sfm_max_runtime, "rows": posing,
                   "note": "frames are rendered at the planned poses, so sim truth equals the nominal rig and "
                           "the rig path's own pose error is zero by construction; its cross-check (each ring "
                           "refitted to the matches, the others held) should find no ring offset and flag no drift"},
        "total_s": round(time.perf_counter() - started, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    console.print(f"wrote {args.out} in {result['total_s']:.0f} s")


if __name__ == "__main__":
    main()
