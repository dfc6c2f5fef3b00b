"""How many planned steps the fast preset needs: NGS trained on one processed scan at several plan lengths.

The NGS phases are fractions of the plan, so a shorter plan builds and freezes the infill earlier; the
extension rule (stopping.py) then trains on while the held-out score says the plan was too short. Each
run is scored on the held-out views against its own infill, and its held-out curve gives speed against
error. The peer is the longest plan, in the same run.

    python bench/plans.py --scan SCAN [--plans 2000,2500,3000] [--seed N] [--eval-every N --whole-plan]

SCAN is a processed scan folder (images/, masks/, poses/), e.g. a `station demo` scan. Writes
bench/results/plans.json and plans.svg. `--whole-plan` turns the early finish off and `--eval-every`
scores more often, so the curve shows where the finish rule (stopping.py) ends a run and what the rest
of the plan would have bought.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from machine import describe
from ngs import curve_svg, score, train_one
from station.ngs.infill import Infill
from station.ngs.presets import make_config
from station.scanfolder import atomic_write_bytes, atomic_write_json

RESULTS = Path(__file__).parent / "results" / "plans.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scan", type=Path, required=True, help="a processed scan folder")
    parser.add_argument("--plans", default="2000,2500,3000", help="comma list of planned step counts")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-every", type=int, help="held-out evaluations every this many steps (default: preset's)")
    parser.add_argument("--whole-plan", action="store_true", help="no early finish: train every planned step")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    plans = sorted(int(p) for p in args.plans.split(","))

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for steps in plans:
            label = f"{steps}-step plan"
            started = time.perf_counter()
            cfg = replace(make_config("ngs", "fast"), steps=steps, seed=args.seed)
            if args.eval_every:
                cfg = replace(cfg, eval_every=args.eval_every)
            if args.whole_plan:
                cfg = replace(cfg, extend=replace(cfg.extend, finish_sos=None))
            run = train_one(args.scan, Path(tmp), label, cfg)
            print(f"{label}: trained in {time.perf_counter() - started:.0f} s", file=sys.stderr)
            own = Infill.from_state_dict(torch.load(run / "model" / "infill.pt", weights_only=True))
            rows[label] = score(run, own)

    peer = rows[f"{plans[-1]}-step plan"]
    result = {
        "benchmark": "plans",
        "machine": {**describe(), "load_average": list(os.getloadavg())},
        "threads": torch.get_num_threads(),
        "scan": str(args.scan),
        "preset": "fast",
        "seed": args.seed,
        "eval_every": args.eval_every,
        "early_finish": not args.whole_plan,
        "peer": f"the {plans[-1]}-step plan, same scan, same run",
        "methods": rows,
        "against_peer": {label: {"time_ratio": round(r["train_seconds"] / peer["train_seconds"], 3),
                                 "psnr_delta_db": round(r["psnr"] - peer["psnr"], 3),
                                 "sos_delta": round(r["sos"] - peer["sos"], 4)} for label, r in rows.items()},
    }
    atomic_write_json(args.out, result)
    svg = args.out.with_suffix(".svg")
    atomic_write_bytes(svg, curve_svg(rows, f"held-out PSNR and SOS against time by plan, {args.scan.name}").encode())

    table = Table(title="NGS by planned steps (fast preset, extensions on)")
    for column in ("plan", "steps", "train s", "PSNR", "SOS", "time / peer", "why it stopped"):
        table.add_column(column, justify="left" if column in ("plan", "why it stopped") else "right")
    for label, r in rows.items():
        table.add_row(label, str(r["steps"]), f"{r['train_seconds']:.0f}", f"{r['psnr']:.2f}", f"{r['sos']:.3f}",
                      f"{result['against_peer'][label]['time_ratio']:.2f}", r["extensions"][-1]["reason"])
    Console().print(table)
    for label, r in rows.items():
        curve = Table(title=f"{label}: held-out figures as it trained (leak: the worst view's infill, px of green)")
        for column in ("step", "s", "PSNR", "SOS", "leak px"):
            curve.add_column(column, justify="right")
        for point in r["held_out_curve"]:
            curve.add_row(str(point["step"]), f"{point['seconds']:.0f}", f"{point['psnr']:.2f}",
                          *(f"{point[k]:.3g}" if point.get(k) is not None else "" for k in ("sos", "leak_px")))
        Console().print(curve)
    print(f"wrote {args.out} and {svg}")


if __name__ == "__main__":
    main()
