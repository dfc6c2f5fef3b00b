"""How many threads torch's own ops get inside a training step: one (the trainer's rule) against the whole pool.

With OMP_WAIT_POLICY=PASSIVE every parallel torch op wakes a sleeping thread, and a training step is many
small ops (activations, the concatenated noise, the losses, Adam). The peer is the step on torch's whole pool,
as the trainer ran before. Both run in one training run, in turns of ten steps, so they see the same model
sizes, views and machine; each turn's median step is paired with its neighbour's. The step that builds the
infill keeps the pool in both and is reported apart. Error axis: both compute the same step (up to the
order of torch's reductions), and the run's held-out PSNR and SOS at its end are given beside the times.

    python bench/step_threads.py [--runs demo,dtu-half,dtu-full] [--scan SCAN] [--turn 10] [--out FILE]

`demo` trains on a simulated demo scan, shot and processed first (about two minutes), or on --scan. `dtu-half`
and `dtu-full` train DTU scan65 from ../shared/data/multiview as bench/real.py does (fast preset), at 1/2 and at
full size (about 6 and 10 minutes).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch and numba load their OpenMP runtimes

import torch  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

import station.ngs.trainer as trainer_module  # noqa: E402
from machine import describe, summary  # noqa: E402
from ngs import compile_kernels_elsewhere, shoot_and_process  # noqa: E402
from real import DATASETS, import_real  # noqa: E402
from station.ngs.dataset import load_scene  # noqa: E402
from station.ngs.presets import make_config  # noqa: E402
from station.ngs.raster import set_num_threads  # noqa: E402
from station.scanfolder import atomic_write_json  # noqa: E402

RESULTS = Path(__file__).parent / "results"
POLICIES = ("one thread", "whole pool")  # this tree's rule, then the peer


def timed_run(scan: Path, downscale: int, turn: int) -> dict:
    """One training run with the policies in turns of `turn` steps -> per-policy step times and pair ratios."""
    cfg = replace(make_config("ngs", "fast"), downscale=downscale)
    scene = load_scene(scan, downscale=cfg.downscale, seed=cfg.seed)
    pool = torch.get_num_threads()
    threads = {POLICIES[0]: trainer_module.STEP_TORCH_THREADS, POLICIES[1]: pool}

    with tempfile.TemporaryDirectory(prefix="step-threads-") as work, contextlib.ExitStack() as undo:
        trainer = trainer_module.Trainer(scene, cfg, Path(work) / "model")
        undo.callback(setattr, trainer_module, "STEP_TORCH_THREADS", trainer_module.STEP_TORCH_THREADS)
        step_once, times, build_step = trainer.train_step, [], trainer.ngs.build_step

        def train_step(step: int) -> dict:
            block = step // turn
            policy = POLICIES[(block + block // 2) % 2]  # ABBA: neither always goes first
            trainer_module.STEP_TORCH_THREADS = threads[policy]
            started = time.perf_counter()
            out = step_once(step)
            times.append((step, policy, time.perf_counter() - started))
            return out

        trainer.train_step = train_step
        report = trainer.run()
        held_out = trainer.held_out()
        view = trainer.train_views()[0]
    build = next(t for s, _, t in times if s == build_step)
    times = [(s, p, t) for s, p, t in times if s != build_step and s > 0]  # the first step pays one-off costs
    per_policy = {p: [t for _, q, t in times if q == p] for p in POLICIES}
    blocks: dict[int, tuple[str, list[float]]] = {}
    for step, policy, seconds in times:
        blocks.setdefault(step // turn, (policy, []))[1].append(seconds)
    ratios = []
    keys = sorted(blocks)
    for a, b in zip(keys[::2], keys[1::2]):
        medians = {blocks[k][0]: statistics.median(blocks[k][1]) for k in (a, b)}
        if len(medians) == 2:
            ratios.append(medians[POLICIES[0]] / medians[POLICIES[1]])
    return {
        "steps": report.steps, "train_seconds": report.seconds, "num_gaussians": report.num_gaussians,
        "num_infill": report.num_infill, "view_size": [view.width, view.height],
        "torch_pool": pool,
        "policies": {p: {"steps": len(v), "median_step_ms": round(1e3 * statistics.median(v), 2),
                         "mean_step_ms": round(1e3 * statistics.fmean(v), 2)} for p, v in per_policy.items()},
        "pair_ratio_median": round(statistics.median(ratios), 3), "pairs": len(ratios),
        "infill_build_step_s": round(build, 2),
        "held_out_psnr": round(held_out["psnr"], 2),
        "held_out_sos": None if held_out.get("sos") is None else round(held_out["sos"], 4),
    }


RUNS = {"demo": ("simulated demo scan", 1), "dtu-half": ("DTU scan65, 1/2 size", 2),
        "dtu-full": ("DTU scan65, full size", 1)}  # name -> (what the results call it, downscale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", default="demo", help=f"comma-separated, of {', '.join(RUNS)}")
    parser.add_argument("--scan", type=Path, help="a processed scan folder for `demo` (default: shoot the demo's)")
    parser.add_argument("--turn", type=int, default=10, help="steps each policy runs before the other")
    parser.add_argument("--out", type=Path, default=RESULTS / "step_threads.json")
    args = parser.parse_args()
    chosen = [name for name in args.runs.split(",") if name]
    if unknown := [name for name in chosen if name not in RUNS]:
        sys.exit(f"step_threads: unknown --runs {', '.join(unknown)} (known: {', '.join(RUNS)})")
    set_num_threads(os.cpu_count() or 1)
    compile_kernels_elsewhere()
    runs = {}
    with tempfile.TemporaryDirectory(prefix="step-threads-scan-") as work:
        for name in chosen:
            label, downscale = RUNS[name]
            if name == "demo":
                scan = args.scan or shoot_and_process(Path(work), None, "320x240")
                label = label if args.scan is None else str(args.scan)
            else:
                scan = import_real("dtu_scan65", DATASETS["dtu_scan65"], Path(work))
            runs[label] = timed_run(scan, downscale, args.turn)
    machine = describe()
    result = {"benchmark": "step_threads", "machine": machine, "load_1min_at_end": round(os.getloadavg()[0], 2),
              "method": f"one training run per scan, policies in ABBA turns of {args.turn} steps",
              "peer": "the whole step on torch's whole pool, as the trainer ran before", "runs": runs}
    atomic_write_json(args.out, result)
    table = Table(title=f"torch threads in a training step ({summary(machine)})")
    for column in ("scan", "view", "gaussians", "one thread ms", "whole pool ms", "ratio", "infill build s",
                   "PSNR", "SOS"):
        table.add_column(column)
    for name, run in runs.items():
        one, peer = (run["policies"][p]["median_step_ms"] for p in POLICIES)
        table.add_row(name, "x".join(map(str, run["view_size"])), f"{run['num_gaussians']}+{run['num_infill']}",
                      f"{one:.1f}", f"{peer:.1f}", f"{run['pair_ratio_median']:.3f}", f"{run['infill_build_step_s']}",
                      f"{run['held_out_psnr']}", f"{run['held_out_sos']}")
    Console().print(table)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
