"""3DGS vs 3DGS+alpha vs NGS on real photos: DTU scan65 and the Middlebury temple ring.

Each dataset is brought in with `station import` (DTU as IDR/NeuS cameras with its own masks; the temple,
which has none, with masks cut from its black backdrop), then the three methods train on the same views
with the same preset and are scored as bench/ngs.py scores a simulated stone: held-out PSNR, SSIM and
SOS against the NGS run's infill (an NGS variant against its own), and held-out PSNR and SOS sampled
during training, so each file holds speed against error. One results file per dataset, in bench/ngs.py's
shape, plus a curve SVG.

    python bench/real.py [--datasets dtu_scan65,temple] [--downscale 2] [--preset fast] [--methods 3dgs,alpha,ngs]
                         [--variants paced,paper-prune] [--budget N] [--work DIR]

With --work the imports and runs are kept there, and a run that already finished (or was killed: it resumes
from its checkpoint) is not trained again, so methods can train in separate processes and be scored together.

Data comes from ../shared/data/multiview (not shipped: DTU and Middlebury have their own licences).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from machine import describe
from ngs import curve_svg, score, train_one
from station.ngs.conventions import ALPHA_MIN
from station.ngs.infill import Infill
from station.ngs.presets import make_config
from station.ngs.trainer import TrainConfig
from station.process.importers import ImportSettings, import_dataset
from station.scanfolder import atomic_write_bytes, atomic_write_json

ROOT = Path(__file__).resolve().parent.parent
MULTIVIEW = ROOT.parent / "shared" / "data" / "multiview"
RESULTS = Path(__file__).parent / "results"


@dataclass(frozen=True)
class RealDataset:
    folder: str
    format: str
    masks: str  # "files": the dataset's own; "dark-backdrop": cut on import
    note: str


DATASETS = {
    "dtu_scan65": RealDataset("dtu_scan65_800x600", "idr", "files",
                              "DTU scan65 (IDR/NeuS release), 49 views, real lens and sensor, masks given"),
    "temple": RealDataset("templeSparseRing", "middlebury", "dark-backdrop",
                          "Middlebury templeSparseRing, 16 views on a ring, black backdrop, no masks given"),
}


VARIANTS = {  # further NGS runs, each one change that real photos may need and simulated stones did not
    "paced": lambda cfg: replace(cfg, densify=replace(cfg.densify, budget_ramp=0.5)),
    "paper-prune": lambda cfg: replace(cfg, ngs=replace(cfg.ngs, infill=replace(cfg.ngs.infill,
                                                                                surface_alpha=ALPHA_MIN))),
}


def import_real(name: str, dataset: RealDataset, work: Path) -> Path:
    source = MULTIVIEW / dataset.folder
    if not source.is_dir():
        sys.exit(f"real: {source} is missing (the shared data sits beside the repository)")
    out = work / name
    if (out / "poses" / "transforms.json").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    settings = ImportSettings() if dataset.masks == "files" else ImportSettings(masks=dataset.masks)
    import_dataset(source, dataset.format, out, settings)
    return out


def scoring_infill(run: Path, ngs_run: Path) -> Infill:
    """A run's own infill when it trained one, else the NGS run's: 3DGS has no inside of its own to hide."""
    own = run / "model" / "infill.pt"
    return Infill.from_state_dict(torch.load(own if own.is_file() else ngs_run / "model" / "infill.pt",
                                             weights_only=True))


def configure(method: str, preset: str, seed: int, downscale: int, budget: int | None) -> TrainConfig:
    cfg = replace(make_config(method, preset), seed=seed, downscale=downscale)
    return cfg if budget is None else replace(cfg, densify=replace(cfg.densify, max_gaussians=budget))


def run_dataset(name: str, dataset: RealDataset, methods: list[str], variants: list[str], preset: str,
                downscale: int, seed: int, work: Path, budget: int | None = None) -> dict | None:
    source = import_real(name, dataset, work)
    runs = {method: configure(method, preset, seed, downscale, budget) for method in methods}
    base = configure("ngs", preset, seed, downscale, budget)
    runs.update({f"ngs, {variant}": VARIANTS[variant](base) for variant in variants})
    trained = {}
    for label, cfg in runs.items():
        started = time.perf_counter()
        trained[label] = train_one(source, work / f"{name}-runs", label, cfg)
        print(f"{name} {label}: trained in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    if "ngs" not in trained:
        print(f"{name}: trained only; SOS needs the NGS run's infill, so scoring waits for a run with ngs",
              file=sys.stderr)
        return None
    rows = {label: score(run, scoring_infill(run, trained["ngs"])) for label, run in trained.items()}
    peers = [PEER_NAMES[m] for m in methods if m != "ngs"]  # the variants are not peers
    best_psnr = max(rows[m]["psnr"] for m in methods)
    psnr_3dgs = rows["3dgs"]["psnr"] if "3dgs" in rows else None
    return {
        "benchmark": "real",
        "machine": {**describe(), "load_average": list(os.getloadavg())},
        "threads": torch.get_num_threads(),
        "scan": f"{dataset.note}; trained at 1/{downscale} of the source size"
                + ("" if budget is None else f", at most {budget:,} Gaussians"),
        "presets": [preset],
        "seed": seed,
        "peer": (f"{' and '.join(peers)}, same preset, same views, same run, scored with the NGS run's infill; "
                 "each NGS variant scored with its own") if peers else "none: NGS alone in this run",
        "methods": rows,
        "ngs_psnr_gap_to_best_db": round(best_psnr - rows["ngs"]["psnr"], 3) if peers else None,
        "ngs_psnr_minus_3dgs_db": None if psnr_3dgs is None else round(rows["ngs"]["psnr"] - psnr_3dgs, 3),
        "ngs_time_over_3dgs": None if psnr_3dgs is None else round(rows["ngs"]["train_seconds"]
                                                                   / rows["3dgs"]["train_seconds"], 3),
        "ngs_first_at_bar": None if psnr_3dgs is None else first_at_bar(rows["ngs"]["held_out_curve"], psnr_3dgs),
    }


PEER_NAMES = {"3dgs": "3dgs", "alpha": "3dgs+alpha"}  # how the peer sentence names each method beside NGS
SOS_BAR, PSNR_MARGIN_DB = 0.85, 0.3  # the real-photo bar: SOS >= 0.85, PSNR within 0.3 dB of our 3DGS


def first_at_bar(curve: list[dict], psnr_3dgs: float) -> dict | None:
    """The first held-out evaluation of a run at the bar: how long a scan needs to train, not how long it did."""
    for point in curve:
        if (point.get("sos") or 0.0) >= SOS_BAR and point["psnr"] >= psnr_3dgs - PSNR_MARGIN_DB:
            return {"step": point["step"], "seconds": point["seconds"], "psnr": round(point["psnr"], 3),
                    "sos": round(point["sos"], 4), "sos_bar": SOS_BAR, "psnr_margin_db": PSNR_MARGIN_DB}
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--datasets", default="dtu_scan65,temple")
    parser.add_argument("--methods", default="3dgs,alpha,ngs")
    parser.add_argument("--variants", default="", help=f"comma list of extra NGS runs: {', '.join(VARIANTS)}")
    parser.add_argument("--work", type=Path, help="keep imports and runs here (default: a temporary folder)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--downscale", type=int, default=2, help="train at 1/N of the source size (DTU: 400x300)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--budget", type=int, help="cap every run's Gaussians at N (default: the preset's cap)")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args()
    names = args.datasets.split(",")
    variants = [v for v in args.variants.split(",") if v]
    unknown = [n for n in names if n not in DATASETS] + [v for v in variants if v not in VARIANTS]
    if unknown:
        sys.exit(f"real: unknown dataset(s) or variant(s) {', '.join(unknown)}; choose from "
                 f"{', '.join(DATASETS)} and {', '.join(VARIANTS)}")

    table = Table(title=f"Real photos: speed against error ({args.preset} preset, 1/{args.downscale} size)")
    for column in ("dataset", "method", "train s", "steps", "Gaussians", "PSNR", "SSIM", "SOS", "PSNR*"):
        table.add_column(column, justify="left" if column in ("dataset", "method") else "right")
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            result = run_dataset(name, DATASETS[name], [m for m in args.methods.split(",") if m], variants, args.preset,
                                 args.downscale, args.seed, args.work or Path(tmp), args.budget)
            if result is None:
                continue
            suffix = "" if args.budget is None else f"_budget{args.budget}"  # a capped run keeps the default's file
            out = args.out_dir / f"real_{name}{suffix}.json"
            atomic_write_json(out, result)
            svg = curve_svg(result["methods"], f"held-out PSNR and SOS against time, {result['scan']}")
            atomic_write_bytes(out.with_suffix(".svg"), svg.encode())
            for method, r in result["methods"].items():
                table.add_row(name, method, f"{r['train_seconds']:.0f}", str(r["steps"]), str(r["num_gaussians"]),
                              f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['sos']:.3f}", f"{r['psnr_star']:.2f}")
            print(f"wrote {out}", file=sys.stderr)
    Console().print(table)


if __name__ == "__main__":
    main()
