"""3DGS vs 3DGS+alpha vs NGS on a simulated stone: held-out PSNR/PSNR*/SSIM, SOS, counts, time.

Each method trains on the same processed scan with the same preset (all three share every step
count and learning rate; only the losses and the infill differ), then is scored with the NGS run's
infill, as the paper does, so SOS compares like with like. `--ablations` adds the paper's
ablations of NGS (no erosion, no pruning, no L_f, no LR reset, no colour reset) and ours (L_f on the
rendered alpha after the freeze, as the reference does, instead of the surface's own). Held-out PSNR and
SOS are sampled during training, so the JSON also holds speed against error for every run. Presets after
the first (`--presets fast,paper`) add an NGS run each, for speed against error across presets.
`--full-resolution-peer` adds the NGS run trained at full resolution from the first step, the peer
of the preset's coarse start (resolution.py).

    python bench/ngs.py [--scan SCAN] [--stone LOOK:SEED] [--size 256x192] [--presets fast[,paper]] [--first-sizes]
                        [--ablations] [--full-resolution-peer] [--seed N]

Without --scan a 6x40 simulated scan is shot and processed first (a few minutes). Writes
bench/results/ngs.json and, beside it, ngs.svg: held-out PSNR and SOS against training time per run.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import asdict, replace
from html import escape
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from station.ngs.dataset import load_scene
from station.ngs.infill import Infill
from station.ngs.pipeline import write_model
from station.ngs.presets import make_config
from station.ngs.resolution import ResolutionConfig
from station.ngs.sos import evaluate, load_surface
from station.ngs.trainer import TrainConfig, Trainer
from station.ngs.warmup import start_kernel_warmup
from station.scanfolder import ScanFolder, atomic_write_bytes, atomic_write_json
from machine import describe

RESULTS = Path(__file__).parent / "results" / "ngs.json"


def ablations(cfg: TrainConfig) -> dict[str, TrainConfig]:
    """The paper's ablations of NGS, each one switch off."""
    ngs, infill = cfg.ngs, cfg.ngs.infill
    return {
        "ngs: no erosion": replace(cfg, ngs=replace(ngs, infill=replace(infill, erosion=False))),
        "ngs: no pruning": replace(cfg, ngs=replace(ngs, infill=replace(infill, depth_prune=False))),
        "ngs: no L_f": replace(cfg, loss=replace(cfg.loss, fg_weight=0.0)),
        "ngs: no LR reset": replace(cfg, ngs=replace(ngs, lr_reset=False)),
        "ngs: no colour reset": replace(cfg, ngs=replace(ngs, recolour=False)),
        "ngs: L_f on the rendered alpha (reference)": replace(cfg, ngs=replace(ngs, fg_on_surface=False)),
    }


def shoot_and_process(root: Path, stone: str | None, size: str) -> Path:
    scan = root / "scan"
    command = [sys.executable, "-m", "station", "scan", "--sim", "--out", str(scan), "--size", size, "--time-scale", "0.01"]
    if stone:
        command += ["--stone", stone]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    subprocess.run([sys.executable, "-m", "station", "process", str(scan)], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return scan


@functools.cache
def compile_kernels_elsewhere() -> None:
    """Fill numba's cache from a child, once per bench: compiled here, a kernel would time its compile in the first
    run, and under fastmath fresh code differs in its last bits from the cached code that later runs load."""
    start_kernel_warmup().join()


def train_one(source: Path, work: Path, name: str, cfg: TrainConfig) -> Path:
    """Train `cfg` on a copy of the posed part of `source`; returns the run's scan folder. A run already
    finished there with the same config is kept (another config trains afresh), and a killed one resumes
    from its checkpoint."""
    run = work / name.replace(" ", "_").replace(":", "")
    finished = run / "model" / "train_metrics.json"
    if finished.is_file() and json.loads(finished.read_text())["config"] == json.loads(json.dumps(asdict(cfg))):
        return run
    for sub in ("images", "masks", "poses"):
        if not (run / sub).is_dir():
            shutil.copytree(source / sub, run / sub)
    compile_kernels_elsewhere()
    scene = load_scene(run, downscale=cfg.downscale, seed=cfg.seed)
    trainer = Trainer(scene, cfg, run / "model")
    write_model(trainer, trainer.run())
    return run


def score(run: Path, infill: Infill) -> dict:
    compile_kernels_elsewhere()  # a bench whose runs all finished earlier renders here first
    scan = ScanFolder(run)
    surface, downscale = load_surface(scan)
    scene = load_scene(run, downscale=downscale)
    metrics = evaluate(surface, infill, scene.test)
    metrics.pop("views")
    train = scan.read_json(scan.model_dir / "train_metrics.json")
    return {**metrics, "steps": train["report"]["steps"], "planned_steps": train["planned_steps"],
            "extensions": train["extensions"], "train_seconds": train["report"]["seconds"],
            "held_out_curve": train["held_out"], "resolution": train["resolution"]}


COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def curve_panel(rows: dict[str, dict], key: str, label: str, top: int, t_max: float) -> str:
    """One 640x300 panel: held-out `key` against training seconds, one polyline per run, final value in the legend."""
    width, height, left, bottom = 640, 300, 60, 40
    curves = {name: [(p["seconds"], p[key]) for p in r["held_out_curve"] if p.get(key) is not None]
              for name, r in rows.items()}
    values = [v for curve in curves.values() for _, v in curve]
    if not values:
        return ""
    lo, hi = min(values), max(values)
    lo, hi = lo - 0.05 * (hi - lo or 1.0), hi + 0.05 * (hi - lo or 1.0)

    def xy(t: float, v: float) -> str:
        return f"{left + (width - left - 20) * t / t_max:.1f},{top + height - bottom - (height - bottom - 30) * (v - lo) / (hi - lo):.1f}"

    parts = [f'<line x1="{left}" y1="{top + height - bottom}" x2="{width - 20}" y2="{top + height - bottom}" stroke="black"/>',
             f'<line x1="{left}" y1="{top + 30}" x2="{left}" y2="{top + height - bottom}" stroke="black"/>',
             f'<text x="{width // 2}" y="{top + height - 8}">training seconds (0 to {t_max:.0f})</text>',
             f'<text x="4" y="{top + 20}">{label} {lo:.3g}-{hi:.3g}</text>']
    for k, (name, curve) in enumerate(curves.items()):
        if not curve:
            continue
        colour = COLOURS[k % len(COLOURS)]
        parts.append(f'<polyline points="{" ".join(xy(t, v) for t, v in curve)}" fill="none" stroke="{colour}" '
                     f'stroke-width="2"/>')
        parts.append(f'<text x="{width - 300}" y="{top + height - bottom - 14 * (len(curves) - k)}" fill="{colour}">'
                     f'{name}: {rows[name][key]:.3f}</text>')
    return "".join(parts)


def curve_svg(rows: dict[str, dict], title: str) -> str:
    """Held-out PSNR (top) and SOS (bottom, once an infill exists) against training seconds."""
    seconds = [p["seconds"] for r in rows.values() for p in r["held_out_curve"]]
    if not seconds:
        return ""
    t_max = max(seconds) or 1.0
    lines = textwrap.wrap(title, 100)  # a long scan description ran past the right edge, cut off
    below = 14 * (len(lines) - 1)
    heading = "".join(f'<text x="60" y="{16 + 14 * i}">{escape(line)}</text>' for i, line in enumerate(lines))
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="640" height="{620 + below}" font-family="sans-serif" '
            f'font-size="11"><rect width="100%" height="100%" fill="white"/>{heading}'
            f'{curve_panel(rows, "psnr", "held-out PSNR dB", 10 + below, t_max)}'
            f'{curve_panel(rows, "sos", "held-out SOS", 320 + below, t_max)}</svg>\n')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scan", type=Path, help="a processed scan folder (default: shoot and process one)")
    parser.add_argument("--stone", default=None, help="simulated stone: seed, look:seed or a mesh path")
    parser.add_argument("--size", default="256x192")
    parser.add_argument("--presets", default="fast",
                        help="comma list: the first trains all three methods, each further one an NGS run")
    parser.add_argument("--ablations", action="store_true")
    parser.add_argument("--first-sizes", action="store_true",
                        help="further presets keep the first preset's Gaussian budget and infill levels (the paper "
                             "preset's own growth does not fit a 2-core CPU: docs/method.md)")
    parser.add_argument("--full-resolution-peer", action="store_true",
                        help="add NGS trained at full resolution throughout, the peer of the preset's coarse start")
    parser.add_argument("--seed", type=int, default=0, help="training seed of every run (run-to-run spread)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        source = args.scan or shoot_and_process(work, args.stone, args.size)
        preset, *more_presets = args.presets.split(",")
        runs = {method: replace(make_config(method, preset), seed=args.seed) for method in ("3dgs", "alpha", "ngs")}
        if args.ablations:
            runs.update(ablations(runs["ngs"]))
        if args.full_resolution_peer:
            runs["ngs: full resolution throughout"] = replace(runs["ngs"], resolution=ResolutionConfig())
        for name in more_presets:
            cfg, label = replace(make_config("ngs", name), seed=args.seed), f"ngs, {name} preset"
            if args.first_sizes:
                first = runs["ngs"]
                cfg = replace(cfg, densify=replace(cfg.densify, max_gaussians=first.densify.max_gaussians,
                                                   per_object_pixel=first.densify.per_object_pixel),
                              ngs=replace(cfg.ngs, infill=first.ngs.infill))
                label += f", {preset} sizes"
            runs[label] = cfg
        trained = {}
        for name, cfg in runs.items():
            started = time.perf_counter()
            trained[name] = train_one(source, work, name, cfg)
            print(f"{name}: trained in {time.perf_counter() - started:.0f} s", file=sys.stderr)
        # One infill for every score: the full NGS run's, the paper's benchmark use of it.
        infill = Infill.from_state_dict(torch.load(trained["ngs"] / "model" / "infill.pt", weights_only=True))
        rows = {name: score(run, infill) for name, run in trained.items()}

    best_psnr = max(rows[method]["psnr"] for method in ("3dgs", "alpha", "ngs"))  # the ablations are not peers
    result = {
        "benchmark": "ngs",
        "machine": describe(),
        "threads": os.cpu_count(),
        "scan": str(args.scan or f"simulated {args.stone or 'default stone'} at {args.size}, 6x40"),
        "presets": args.presets.split(","),
        "seed": args.seed,
        "further_presets_on_first_sizes": args.first_sizes,
        "peer": "3dgs and 3dgs+alpha, same preset, same run, scored with the NGS infill",
        "methods": rows,
        "ngs_psnr_gap_to_best_db": round(best_psnr - rows["ngs"]["psnr"], 3),
    }
    peer = rows.get("ngs: full resolution throughout")
    if peer:
        result["coarse_start_against_full_resolution"] = {
            "time_ratio": round(rows["ngs"]["train_seconds"] / peer["train_seconds"], 3),
            "seconds_per_step_ratio": round((rows["ngs"]["train_seconds"] / rows["ngs"]["steps"])
                                            / (peer["train_seconds"] / peer["steps"]), 3),
            "psnr_delta_db": round(rows["ngs"]["psnr"] - peer["psnr"], 3),
            "sos_delta": round(rows["ngs"]["sos"] - peer["sos"], 4),
        }
    atomic_write_json(args.out, result)
    svg = args.out.with_suffix(".svg")
    atomic_write_bytes(svg, curve_svg(rows, f"held-out PSNR and SOS against time, {result['scan']}").encode())

    table = Table(title=f"NGS against its baselines ({preset} preset)")
    for column in ("method", "PSNR", "PSNR*", "SSIM", "SOS", "Gaussians", "scoring infill", "steps", "train s"):
        table.add_column(column, justify="right" if column != "method" else "left")
    for name, r in rows.items():
        table.add_row(name, f"{r['psnr']:.2f}", f"{r['psnr_star']:.2f}", f"{r['ssim']:.4f}", f"{r['sos']:.3f}",
                      str(r["num_gaussians"]), str(r["num_infill"]), str(r["steps"]), f"{r['train_seconds']:.0f}")
    Console().print(table)
    if peer:
        print(f"coarse start against full resolution throughout: {result['coarse_start_against_full_resolution']}")
    print(f"wrote {args.out} and {svg}")


if __name__ == "__main__":
    main()
