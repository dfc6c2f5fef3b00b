"""Train a scan folder end to end: pick the preset, load the posed views, train, write model/.

`station/pipeline.py` calls `train_scan` with the model folder staged; everything it writes goes through
the atomic writers.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path
from typing import Callable

import torch

from station.ngs.dataset import load_scene
from station.ngs.presets import make_config
from station.ngs.sh_degree import cut_to_degree, sh_degree_choice
from station.ngs.trainer import Trainer, TrainReport
from station.scanfolder import ScanFolder, atomic_write_json, atomic_write_with


def write_model(trainer: Trainer, report: TrainReport) -> None:
    """model/surface.pt (colour cut to the SH degree the held-out views need), model/infill.pt (NGS) and
    model/train_metrics.json, each atomically."""
    model_dir = trainer.model_dir
    # the run's last held-out evaluation is at its final step: no need to render the views again
    trained_psnr = trainer.evals[-1]["psnr"] if trainer.evals else trainer.held_out_psnr()
    sh_choice = sh_degree_choice(trainer.cfg.sh_degree, trained_psnr, trainer.held_out_psnr,
                                 trainer.cfg.sh_tolerance_db)
    surface = {
        "params": cut_to_degree(trainer.model.state_dict(), sh_choice["kept"]),
        "sh_degree": sh_choice["kept"],
        "scene_scale": trainer.scene.scene_scale,
        "downscale": trainer.cfg.downscale,
        "method": trainer.cfg.method,
    }
    atomic_write_with(model_dir / "surface.pt", lambda tmp: torch.save(surface, tmp))
    infill_path = model_dir / "infill.pt"
    if trainer.ngs and trainer.ngs.infill is not None:
        infill = trainer.ngs.infill.state_dict()
        atomic_write_with(infill_path, lambda tmp: torch.save(infill, tmp))
    else:
        infill_path.unlink(missing_ok=True)  # a stale infill from another method must not score this model
    metrics = {
        "report": asdict(report),
        "config": asdict(trainer.cfg),
        "losses": trainer.losses,
        "held_out": trainer.evals,
        "planned_steps": trainer.cfg.steps,
        "extensions": trainer.extensions,
        "sh_degree": sh_choice,
        "gaussian_budget": trainer.gaussian_budget,
        "resolution": {"start_downscale": trainer.cfg.resolution.start_downscale, "final_downscale": trainer.level_downscale,
                       "checks": trainer.resolution_checks},
        "densify": trainer.strategy.state.history,
        "ngs": trainer.ngs.history if trainer.ngs else [],
    }
    atomic_write_json(model_dir / "train_metrics.json", metrics)


def train_scan(scan_root: Path | ScanFolder, method: str = "ngs", preset: str = "fast",
               progress: Callable[[int, dict], None] | None = None, inputs: str = "") -> TrainReport:
    """Train `method` with `preset` on a posed scan folder; resumes from model/checkpoint.pt when it was
    written from the same `inputs` (the fingerprint of the posed views)."""
    scan = scan_root if isinstance(scan_root, ScanFolder) else ScanFolder(scan_root)
    cfg = make_config(method, preset)
    scene = load_scene(scan.root, downscale=cfg.downscale, seed=cfg.seed)
    trainer = Trainer(scene, cfg, scan.model_dir, inputs)
    # a staged view trains in `.model.new`; the report names the folder the model is swapped into
    report = replace(trainer.run(progress), model_dir=str(ScanFolder(scan.root).model_dir))
    write_model(trainer, report)
    scan.mark_done("train", asdict(report))
    return report
