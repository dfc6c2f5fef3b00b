"""docs/evidence.md from bench/results/*.json: every figure the project quotes, as tables and plots.

The bench scripts write the measurements; this page is generated from them so that no figure lives
only in prose, where it goes stale. Each results file gets a section: a known benchmark its own
table and, where its script draws none, a speed-against-error plot written beside the JSON; any other
file a table of its top-level figures, so nothing measured goes unreported.

    python bench/report.py [--results bench/results] [--out docs/evidence.md]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))
from machine import summary  # noqa: E402
from svgplot import Series, scatter_svg  # noqa: E402

from station.errors import BadInputError  # noqa: E402
from station.scanfolder import atomic_write_bytes, atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
Section = tuple[list[str], dict[str, str]]  # markdown lines, {plot file name: SVG text}


def table(header: list[str], rows: list[list[object]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out + [""]


def num(value: object, digits: int = 3) -> str:
    """A table cell: floats to `digits` places, integers with thousands separators, booleans as yes/no."""
    match value:
        case None:
            return ""
        case bool():
            return "yes" if value else "no"
        case int():
            return f"{value:,}"
        case float():
            return f"{value:.{digits}f}"
    return str(value)


def kind_of(data: dict) -> str:
    if data.get("benchmark") in ("demo", "plans", "thread_pools", "spin_count", "step_threads"):
        return data["benchmark"]
    if data.get("benchmark") == "raster" and "before" in data:
        return "raster_ab"
    methods = data.get("methods")
    if isinstance(methods, dict) and methods:
        first = next(iter(methods.values()))
        if isinstance(first, dict) and "held_out_curve" in first:
            return "real" if data.get("benchmark") == "real" else "ngs"
        if isinstance(first, dict) and "chamfer_fraction_of_diagonal" in first:
            return "mesh"
    if "seconds_per_mask" in data and "summary" in data:
        return "masks"
    if data.get("stones") and "first_cut" in data["stones"][0].get("rings", [{}])[0]:
        return "cross_view"
    if "develop" in data and "posing" in data:
        return "process"
    rows = data.get("rows")
    if isinstance(rows, list) and rows and isinstance(rows[0], dict) and "psnr_band_db" in rows[0]:
        return "fidelity"
    configs = data.get("configs") or [{}]
    if "nodes" in configs[0] and "scans_per_hour" in configs[0]:
        return "batch_nodes"
    if "step_ms" in configs[0]:
        return "raster"
    if "scans_per_hour" in configs[0]:
        return "batch"
    if "frames_per_min" in configs[0]:
        return "scan"
    return "other"


def sos_at_plan(run: dict) -> str:
    """Held-out SOS at the planned step count, which compares runs that trained on for different lengths."""
    at = [p["sos"] for p in run["held_out_curve"] if p["step"] == run["planned_steps"] and p.get("sos") is not None]
    return num(at[0]) if at else ""


def ngs_section(name: str, data: dict) -> Section:
    rows = [[run, num(r["psnr"], 2), num(r["psnr_star"], 2), num(r["ssim"], 4), num(r["sos"]), sos_at_plan(r),
             num(r["num_gaussians"]), num(r.get("num_infill")), f"{num(r['steps'])} ({num(r['planned_steps'])})",
             num(r["train_seconds"], 0)]
            for run, r in data["methods"].items()]
    lines = [f"Scan: {data['scan']}; presets {', '.join(data['presets'])}; training seed {data['seed']}. "
             f"Peer: {data['peer']}. SOS at the plan is the held-out SOS at the planned step count against the "
             "run's own training infill, where the run has one.", ""]
    lines += table(["run", "PSNR dB", "PSNR* dB", "SSIM", "SOS", "SOS at the plan", "Gaussians", "infill scored",
                    "steps (planned)", "train s"], rows)
    if data["ngs_psnr_gap_to_best_db"] is not None:  # None: no peer ran beside NGS
        lines.append(f"NGS's held-out PSNR below the best of 3DGS, 3DGS + alpha and NGS: "
                     f"{data['ngs_psnr_gap_to_best_db']:.3f} dB.")
    bar = data.get("ngs_first_at_bar")
    if bar:
        lines.append(f"NGS first at SOS ≥ {bar['sos_bar']} with PSNR within {bar['psnr_margin_db']} dB of 3DGS: step "
                     f"{bar['step']}, {bar['seconds']:.0f} s (PSNR {bar['psnr']:.2f} dB, SOS {bar['sos']:.3f}).")
    elif data.get("ngs_psnr_minus_3dgs_db") is not None:  # 3DGS ran, and NGS never met the bar
        lines.append("NGS never reached SOS ≥ 0.85 with PSNR within 0.3 dB of 3DGS in this run.")
    coarse = data.get("coarse_start_against_full_resolution")
    if coarse:
        lines.append(f"Coarse start against full resolution throughout: seconds per step ×{coarse['seconds_per_step_ratio']}, "
                     f"PSNR {coarse['psnr_delta_db']:+.3f} dB, SOS {coarse['sos_delta']:+.4f}.")
    return lines + [""], {}


def plans_section(name: str, data: dict) -> Section:
    rows = [[run, f"{num(r['steps'])} ({num(r['planned_steps'])})", num(r["train_seconds"], 0),
             num(data["against_peer"][run]["time_ratio"], 2), num(r["psnr"], 2), num(r["sos"]), sos_at_plan(r),
             r["extensions"][-1]["reason"] if r["extensions"] else ""]
            for run, r in data["methods"].items()]
    finish = "early finish on" if data.get("early_finish", True) else "early finish off"
    lines = [f"Scan: {data['scan']}; {data['preset']} preset, extensions on, {finish}; training seed {data['seed']}. "
             f"Peer: {data['peer']}. PSNR and SOS on the held-out views, each run against its own infill.", ""]
    lines += table(["run", "steps (planned)", "train s", "time / peer", "PSNR dB", "SOS", "SOS at the plan",
                    "why it stopped"], rows)
    for run, r in data["methods"].items():
        if any("leak_px" in point for point in r["held_out_curve"]):
            lines += [f"{run}, held-out figures as it trained; leak: the most infill any held-out view shows, in "
                      "pixels' worth of full green (the early finish needs it below 1/510).", ""]
            lines += table(["step", "s", "PSNR dB", "SOS", "leak px"],
                           [[num(p["step"]), num(p["seconds"], 0), num(p["psnr"], 2), num(p.get("sos")),
                             f"{p['leak_px']:.2g}" if p.get("leak_px") is not None else ""]
                            for p in r["held_out_curve"]])
    return lines, {}


def masks_section(name: str, data: dict) -> Section:
    by_stone: dict[str, dict[str, list[dict]]] = {}
    for row in data["summary"]:
        by_stone.setdefault(row["stone"], {}).setdefault(row["method"], []).append(row)
    methods = list(dict.fromkeys(row["method"] for row in data["summary"]))
    rows = [[stone] + [", ".join(f"{r['iou_mean']:.3f}" for r in sorted(found.get(m, []), key=lambda r: r["ring"]))
                       for m in methods] for stone, found in by_stone.items()]
    speed = data["seconds_per_mask"]
    lines = [f"{data['views_per_ring']} views a ring at {data['size'][0]}×{data['size'][1]}; mean IoU against the "
             "simulator's truth per ring, lowest ring first.", ""]
    lines += table(["stone"] + methods, rows)
    lines += [f"Seconds a mask: {', '.join(f'{k} {v}' for k, v in speed.items())}.", ""]
    flows = data["max_flow"]
    lines += [f"Max-flow, on the {flows['graphs']} graphs our masks cut (mean {flows['nodes_mean']:.0f} nodes): "
              f"ours {flows['ours_ms']} ms a graph, scipy's Dinic {flows['scipy_dinic_ms']} ms "
              f"(ratio {flows['ours_over_scipy']}); the same cut on {flows['same_cut']} of {flows['graphs']}.", ""]
    series = [Series(m, [(sum(r["seconds_mean"] for r in found[m]) / len(found[m]),
                          1.0 - sum(r["iou_mean"] for r in found[m]) / len(found[m]))
                         for found in by_stone.values() if m in found]) for m in methods]
    svg = scatter_svg(f"{name}: mask error against time, one point a stone", "seconds a mask",
                      "1 - mean IoU (log)", series, log_y=True)
    return lines, {f"{name}.svg": svg}


def cross_view_section(name: str, data: dict) -> Section:
    sensor = f"{data['sensor'][0]}×{data['sensor'][1]}"
    rows, series = [], []
    for stone in data["stones"]:
        rings = stone["rings"]
        low, recut = rings[0], stone["recut_views"]

        def iou(ring: dict, key: str) -> float:
            return ring[key]["iou_mean"]

        above = [iou(r, "across_rings") for r in rings[1:]]
        whole_first = sum(iou(r, "first_cut") for r in rings) / len(rings)
        whole = sum(iou(r, "across_rings") for r in rings) / len(rings)
        rows.append([stone["stone"], f"{iou(low, 'first_cut'):.4f} → {iou(low, 'across_rings'):.4f} "
                     f"({recut.get(str(low['elevation_deg']), 0)} cut again)",
                     f"{min(above):.3f}-{max(above):.3f}" if above else "", f"{whole_first:.4f} → {whole:.4f}",
                     num(stone["seconds"]["develop_and_first_cut"], 0), num(stone["seconds"]["across_rings"], 0)])
        first_s = stone["seconds"]["develop_and_first_cut"]
        series.append(Series(stone["stone"], [(first_s, 1.0 - iou(low, "first_cut")),
                                              (first_s + stone["seconds"]["across_rings"],
                                               1.0 - iou(low, "across_rings"))], joined=True))
    trained = f", averaged down to {data['training_width']} px wide" if data.get("training_width") else ""
    lines = [f"Full 6×{data['azimuths']} scans shot at {sensor}{trained}; IoU per ring against the simulator's "
             "truth after the first cut and after the cut across rings, in the same run.", ""]
    lines += table(["stone", "lowest ring", "rings above (after)", "whole scan", "develop + first cut s",
                    "across rings s"], rows)
    svg = scatter_svg(f"{name}: lowest ring, first cut -> cut across rings", "seconds (develop and mask)",
                      "1 - IoU, lowest ring (log)", series, log_y=True)
    return lines, {f"{name}.svg": svg}


def raster_section(name: str, data: dict) -> Section:
    rows = [[num(c["gaussians"]), f"{c['width']}×{c['height']}", c["sh_degree"], num(c["step_ms"], 1),
             num(c.get("step_best_ms"), 1), num(c["forward_ms"], 1), num(c["reference_step_ms"], 0),
             num(c["speedup_vs_reference"], 0), c["role"]]
            for c in data["configs"]]
    lines = [f"One training step (forward and backward), {data['threads']} threads, torch {data['torch']}, "
             f"numba {data['numba']}; the plain-torch reference timed where it fits.", ""]
    lines += table(["Gaussians", "image", "SH", "step ms", "fastest step ms", "forward ms", "reference ms", "speed-up",
                    "role"], rows)
    lines += [f"Peak memory {data['peak_rss_mb']} MB (whole run), {data['peak_rss_100k_512_mb']} MB at 100k Gaussians "
              f"and 512²; cold start with a warm numba cache {data['cold_start_ms']} ms. The rasteriser's error "
              "against the reference is pinned by the tests, so the plot is of cost alone.", ""]
    series = [Series(role, [(c["gaussians"] * c["width"] * c["height"], c["step_ms"])
                            for c in data["configs"] if c["role"] == role])
              for role in dict.fromkeys(c["role"] for c in data["configs"])]
    svg = scatter_svg(f"{name}: step time against size", "Gaussians × pixels (log)", "ms a step (log)", series,
                      log_x=True, log_y=True)
    return lines, {f"{name}.svg": svg}


def raster_ab_section(name: str, data: dict) -> Section:
    keys = (("step_ms", "step wall"), ("step_cpu_ms", "step CPU"), ("train_step_ms", "step + Adam wall"))
    rows = [[num(c["gaussians"]), f"{c['width']}×{c['height']}"]
            + [f"{num(c['median'][f'before_{key}'], 1)} → {num(c['median'][f'after_{key}'], 1)} "
               f"(×{c['median'][f'after_{key}'] / c['median'][f'before_{key}']:.2f})" for key, _ in keys]
            + [num(c["median_load_1min"], 1)] for c in data["configs"]]
    lines = [f"One training step of `bench/raster.py`'s scene, {data['threads']} threads: revision {data['before']} "
             f"against {data['after']}, both imported into one process and run in {data['rounds']} turns each, so both "
             "see the same machine; medians in ms, after / before in brackets.", ""]
    lines += table(["Gaussians", "image"] + [label for _, label in keys] + ["1-min load"], rows)
    return lines, {}


def thread_pools_section(name: str, data: dict) -> Section:
    rows = [[c["way"], c["threads"], c["layer"], c["torch_threads"], num(c["step_ms"], 1), num(c["ratio_vs_peer"], 2),
             num(c["mean_step_ms"], 1), num(c["mean_ratio_vs_peer"], 2), num(c["load_1min"], 2)]
            for c in data["configs"]]
    lines = [f"`bench/raster.py`'s step ({num(data['gaussians'])} Gaussians, {data['size'][0]}²) inside a batch stage "
             "process forked from the local executor's forkserver, its pools sized by `limit_threads` or by the peer "
             "(numba's workqueue layer, the way before); medians over rounds run in turns, in ms. Same step, so no "
             "error axis.", ""]
    lines += table(["way", "threads", "numba layer", "torch threads", "median ms", "× peer", "mean ms", "× peer",
                    "1-min load"], rows)
    return lines, {}


def spin_count_section(name: str, data: dict) -> Section:
    rows = [["loaded" if c["loaded"] else "quiet", c["spin_count"], num(c["step_ms"], 1), num(c["ratio_vs_passive"], 2),
             num(c["mean_step_ms"], 1), num(c["mean_ratio_vs_passive"], 2), num(c["cpu_ms"], 1), num(c["load_1min"], 2)]
            for c in data["configs"]]
    lines = [f"`bench/raster.py`'s step ({num(data['gaussians'])} Gaussians, {data['size'][0]}², 2 threads) with "
             "OMP_WAIT_POLICY=PASSIVE and libgomp's GOMP_SPINCOUNT, each in a fresh process, in turns; the peer is 0 "
             f"(passive: sleep at once). Load: {data['load']}. Medians over {data['rounds']} rounds, in ms. Same "
             "step, so no error axis.", ""]
    lines += table(["machine", "GOMP_SPINCOUNT", "median ms", "× passive", "mean ms", "× passive", "CPU ms a step",
                    "1-min load"], rows)
    return lines, {}


def step_threads_section(name: str, data: dict) -> Section:
    rows = []
    for scan, run in data["runs"].items():
        one, pool = (run["policies"][p] for p in ("one thread", "whole pool"))
        rows.append([scan, "x".join(map(str, run["view_size"])), f"{num(run['num_gaussians'])} + {num(run['num_infill'])}",
                     num(run["steps"]), num(one["median_step_ms"], 1), num(pool["median_step_ms"], 1),
                     num(run["pair_ratio_median"], 3), num(run["infill_build_step_s"], 2), num(run["held_out_psnr"], 2),
                     num(run["held_out_sos"], 3)])
    lines = [f"torch's ops in each training step on one thread (the trainer's rule); peer: {data['peer']}. Method: "
             f"{data['method']}. Median step ms; the ratio is the median over neighbouring turns of one thread / whole "
             f"pool. The infill build keeps the pool in both. 1-min load at the end: {data['load_1min_at_end']}.", ""]
    lines += table(["scan", "final view", "Gaussians + infill", "steps", "one thread ms", "whole pool ms", "ratio",
                    "infill build s", "held-out PSNR", "SOS"], rows)
    return lines, {}


def mesh_section(name: str, data: dict) -> Section:
    rows = [[method, num(m["seconds"], 1), num(m["faces"]), num(m["watertight"]),
             f"{100 * m['chamfer_fraction_of_diagonal']:.2f} %", num(m["fscore"]), f"{100 * m['volume_rel_error']:+.1f} %"]
            for method, m in data["methods"].items()]
    lines = [f"Scan: {data['scan']}. Peer: {data['peer']}.", ""]
    lines += table(["surface", "s", "faces", "watertight", "Chamfer-L1 of diagonal", "F-score@1 %", "volume"], rows)
    series = [Series(method, [(m["seconds"], 100 * m["chamfer_fraction_of_diagonal"])])
              for method, m in data["methods"].items()]
    svg = scatter_svg(f"{name}: mesh error against time", "seconds", "Chamfer-L1, % of the diagonal", series)
    return lines, {f"{name}.svg": svg}


def process_section(name: str, data: dict) -> Section:
    develop, posing = data["develop"], data["posing"]
    lines = [f"Develop, {develop['repeats']} repeats; peer: {develop['peer']}.", ""]
    lines += table(["source", "kind", "MP", "ours s", "peer s", "ours / peer"],
                   [[r["source"], r["kind"], num(r["megapixels"]), num(r["ours_s"], 3), num(r["rawpy_default_s"], 3),
                     num(r["ours_over_rawpy"], 2)] for r in develop["rows"]])
    lines += [f"Posing a scan of a {posing['scan']['stone']}: {posing['note']}.", ""]
    rows = []
    for r in posing["rows"]:
        check = r.get("cross_check") or {}
        rows.append([r["views"], r["method"], num(r["seconds"], 1), r["registered"], num(r["reprojection_error_px"]),
                     f"{r['rotation_median_deg']:.2f} / {r['rotation_max_deg']:.2f}",
                     f"{r['centre_median_pct']:.2f} / {r['centre_max_pct']:.2f}",
                     f"{check['ring_rotation_max_deg']:.2f}° / {check['ring_centre_max_pct']:.2f} % "
                     f"(drift flagged: {check['drift_flagged_elevations']})" if check else ""])
    lines += table(["views", "method", "s", "registered", "reprojection px", "rotation median / max °",
                    "centre median / max %", "cross-check: largest ring refit"], rows)
    series = [Series("free SfM", [(r["seconds"], r["rotation_median_deg"])
                                  for r in posing["rows"] if r["method"] == "sfm"], True)]
    svg = scatter_svg(f"{name}: pose error against time (40, 120, 240 views)", "seconds to pose",
                      "median rotation error, degrees", series)
    return lines, {f"{name}.svg": svg}


def batch_section(name: str, data: dict) -> Section:
    rows = [[c["workers"], c["threads_per_stage"], c["scans"], num(c["wall_s"], 1), num(c["scans_per_hour"], 0),
             num(c["overhead_median_s"], 3), ", ".join(sorted(set(c["verdicts"])))] for c in data["configs"]]
    scan = data["scan"]
    lines = [f"{scan['elevations']}×{scan['azimuths']} scans at {scan['size'][0]}×{scan['size'][1]}, preset "
             f"{scan['preset']}. Peer: {data['peer']}. Throughput only: no error axis.", ""]
    lines += table(["workers", "threads a stage", "scans", "wall s", "scans / hour", "overhead a stage s", "verdicts"],
                   rows)
    extra = {k: v for k, v in data.items() if k.startswith("speedup")}
    return lines + [", ".join(f"{k} {v}" for k, v in extra.items()) + ".", ""] if extra else lines, {}


def fidelity_section(name: str, data: dict) -> Section:
    rows = [[r["stone"], num(r["elevation_deg"], 0), r["views"], num(r["false_colour_per_view"], 2),
             num(r["psnr_band_db"], 2), num(r["psnr_stone_db"], 2), num(r["psnr_plate_db"], 2),
             num(r["delta_e00_stone"], 3), num(r["iou_mean"], 4), num(r["matte_s_per_view"], 2)] for r in data["rows"]]
    scan = data["scan"]
    lines = [f"{data.get('label', name)}. Shot at {scan['size'][0]}×{scan['size'][1]}, trained at "
             f"{scan['training_width']} px wide; metrics defined in `{data.get('metrics', 'sim/fidelity.py')}`.", ""]
    lines += table(["stone", "ring °", "views", "false colour / view", "band PSNR dB", "stone PSNR dB",
                    "plate PSNR dB", "ΔE00", "IoU", "matte s / view"], rows)
    return lines, {}


def batch_nodes_section(name: str, data: dict) -> Section:
    rows = [[c["nodes"], c["scans"], num(c["wall_s"], 1), num(c["scans_per_hour"], 0),
             ", ".join(sorted(set(c["verdicts"])))] for c in data["configs"]]
    scan = data["scan"]
    lines = [f"Ray {data.get('ray', '?')}, {scan['elevations']}×{scan['azimuths']} scans at {scan['size'][0]}×"
             f"{scan['size'][1]}, preset {scan['preset']}. {data['machine'].get('note', '')}", ""]
    lines += table(["nodes", "scans", "wall s", "scans / hour", "verdicts"], rows)
    return lines, {}


def scan_section(name: str, data: dict) -> Section:
    rows = [[c["mode"], c["frames"], num(c["wall_s"], 1), num(c["motion_s"], 1), num(c["exposure_s"], 1),
             num(c["overhead_s"], 1), num(c["frames_per_min"], 1)] for c in data["configs"]]
    lines = [f"Simulated rig, {data['size'][0]}×{data['size'][1]}, {len(data['plan']['elevations_deg'])} rings of "
             f"{data['plan']['azimuths']}. Throughput only: no error axis.", ""]
    lines += table(["mode", "frames", "wall s", "motion s", "exposure s", "overhead s", "frames / min"], rows)
    lines += [f"Overlap hides {data['overlap_hides_s']} s; speed-up against sequential ×{data['speedup_vs_sequential']}.",
              ""]
    return lines, {}


def demo_section(name: str, data: dict) -> Section:
    runs = data["runs"]
    order = ["scan", "process", "process/develop", "process/poses", "process/masks across rings", "train", "export"]
    stages = sorted({stage for run in runs.values() for stage in run["stages_s"]},
                    key=lambda stage: order.index(stage) if stage in order else len(order))
    rows = [[stage, *(num(run["stages_s"].get(stage), 1) if stage in run["stages_s"] else "–" for run in runs.values())]
            for stage in stages]
    if any("train_steps" in run for run in runs.values()):
        rows.append(["steps trained (planned)", *(f"{num(run['train_steps'])} ({num(run['planned_steps'])})"
                                                  if "train_steps" in run else "–" for run in runs.values())])
    for key in ("PSNR", "SOS"):
        rows.append([key, *(num(run["gate"].get(key)) for run in runs.values())])
    rows.append(["gate passed", *(num(run["gate_passed"]) for run in runs.values())])
    rows.append(["1-min load before / after", *(f"{run['load_1min_before']} / {run['load_1min_after']}"
                                                for run in runs.values())])
    lines = [f"`station demo` end to end, seconds by stage, from the demo's own summary ({data['note']}).", ""]
    lines += table(["stage", *(f"{name} ({run['revision']})" for name, run in runs.items())], rows)
    if "total_ratio_after_over_before" in data:
        lines += [f"Total, after / before: ×{data['total_ratio_after_over_before']}.", ""]
    return lines, {}


def other_section(name: str, data: dict) -> Section:
    flat = {k: v for k, v in data.items() if not isinstance(v, (dict, list))}
    nested = [k for k, v in data.items() if isinstance(v, (dict, list))]
    lines = ["No table of its own here yet; its top-level figures:", ""]
    lines += table(["key", "value"], [[k, num(v)] for k, v in flat.items()]) if flat else []
    if nested:
        lines += [f"Nested: {', '.join(f'`{k}`' for k in nested)}.", ""]
    return lines, {}


def real_runs_summary(files: list[tuple[Path, dict]]) -> list[str]:
    """One table of every NGS run on each real scan (a Gaussian budget is part of the scan's line), across files: a
    single run's SOS moves with the seed and the revision, and only the spread says whether a change moved it."""
    lines: list[str] = []
    for scan in sorted({data["scan"] for _, data in files if "ngs" in data["methods"]}):
        runs = [(path, data, data["methods"]["ngs"]) for path, data in files
                if data["scan"] == scan and "ngs" in data["methods"]]
        rows = [[path.name, data["seed"], num(r["num_gaussians"]), num(r["steps"]), num(r["train_seconds"], 0),
                 num(r["psnr"], 2), num(r["sos"])] for path, data, r in runs]
        lines += [f"NGS on {scan}: every run, one a file.", ""]
        lines += table(["file", "seed", "Gaussians", "steps", "train s", "PSNR dB", "SOS"], rows)
        if len(runs) > 1:
            sos = [r["sos"] for _, _, r in runs]
            seconds = [r["train_seconds"] for _, _, r in runs]
            lines += [f"Over these {len(runs)} runs: SOS median {statistics.median(sos):.3f}, range {min(sos):.3f} "
                      f"to {max(sos):.3f}; train s {min(seconds):.0f} to {max(seconds):.0f}.", ""]
    return lines


SUMMARIES: dict[str, Callable[[list[tuple[Path, dict]]], list[str]]] = {"real": real_runs_summary}

SECTIONS: dict[str, tuple[str, Callable[[str, dict], Section]]] = {
    "demo": ("The demo, stage by stage", demo_section),
    "scan": ("Scanning on the simulated rig", scan_section),
    "process": ("Developing and posing", process_section),
    "masks": ("Masks, one view at a time", masks_section),
    "cross_view": ("Masks cut again across rings", cross_view_section),
    "raster": ("Rasteriser speed", raster_section),
    "raster_ab": ("Rasteriser speed", raster_ab_section),
    "ngs": ("NGS against its baselines", ngs_section),
    "plans": ("How many steps the plan needs", plans_section),
    "real": ("NGS on real photos", ngs_section),
    "mesh": ("Mesh surface", mesh_section),
    "fidelity": ("Training views against the truth", fidelity_section),
    "batch": ("Batch throughput", batch_section),
    "thread_pools": ("Thread pools in a stage process", thread_pools_section),
    "spin_count": ("How long idle OpenMP threads spin", spin_count_section),
    "step_threads": ("torch's threads inside a training step", step_threads_section),
    "batch_nodes": ("Batch throughput", batch_nodes_section),
    "other": ("Other results", other_section),
}
SCRIPTS = {"cross_view": "cross_view", "fidelity": "process", "batch_nodes": "batch", "raster_ab": "raster"}


def load(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInputError(f"{path}: not a readable results file ({exc})") from exc
    if not isinstance(data, dict):
        raise BadInputError(f"{path}: expected a JSON object of results")
    return data


def machine_line(data: dict) -> str:
    return f"Machine: {summary(data.get('machine') or {})}."


def render(results: Path, out: Path) -> tuple[str, dict[Path, str]]:
    """The page's markdown and the plots to write, {path: SVG}; links are relative to `out`'s folder."""
    files = sorted(results.glob("*.json"))
    if not files:
        raise BadInputError(f"{results}: no results files (*.json)")
    loaded = [(path, load(path)) for path in files]
    order = list(SECTIONS)
    loaded.sort(key=lambda item: (order.index(kind_of(item[1])), item[0].name))
    link_root = Path(os.path.relpath(results, out.parent))
    lines = ["# Evidence", "",
             "Generated by `./dev bench report` (`bench/report.py`) from `bench/results/*.json`; do not edit by hand.",
             "Each results file is written by the bench script named under it, which prints the same table. Timings",
             "come from a shared 2-core machine unless the file says otherwise: compare within one table only.", ""]
    plots: dict[Path, str] = {}
    current = None
    for path, data in loaded:
        kind = kind_of(data)
        title, section = SECTIONS[kind]
        if title != current:
            lines += [f"## {title}", ""]
            current = title
            if kind in SUMMARIES:
                lines += SUMMARIES[kind]([item for item in loaded if kind_of(item[1]) == kind])
        script = SCRIPTS.get(kind, data.get("benchmark") or kind)
        body, drawn = section(path.stem, data)
        lines += [f"### {path.name}", "",
                  f"[`bench/results/{path.name}`]({(link_root / path.name).as_posix()}), from `bench/{script}.py`. "
                  + machine_line(data), ""]
        lines += body
        for svg_name, svg in drawn.items():
            plots[results / svg_name] = svg
        plot = results / f"{path.stem}.svg"
        if plot in plots or plot.exists():
            lines += [f"![{path.stem}: speed against error]({(link_root / plot.name).as_posix()})", ""]
    return "\n".join(lines).rstrip() + "\n", plots


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=ROOT / "bench" / "results")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "evidence.md")
    args = parser.parse_args()
    try:
        page, plots = render(args.results, args.out)
    except BadInputError as exc:
        sys.exit(f"report: {exc}")
    for path, svg in plots.items():
        atomic_write_bytes(path, svg.encode())
    atomic_write_text(args.out, page)
    print(f"wrote {args.out} ({len(page):,} bytes) and {len(plots)} plots in {args.results}")


if __name__ == "__main__":
    main()
