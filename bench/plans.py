"""How many planned steps the fast preset needs: NGS trained on one processed scan at several plan lengths.

The NGS phases are fractions of the plan, so a shorter plan builds and freezes the infill earlier; the
extension rule (stopping.py) then trains on while the held-out score says the plan was too short. Each
run is scored on the held-out views against its own infill, and its held-out curve gives speed against
error. The peer is the longest plan, in the same run.

    python bench/plans.py --scan SCAN [--plans 2000,2500,3000] [--seed N]

SCAN is a processed scan folder (images/, masks/, poses/), e.g. a `station demo` scan. Writes
bench/results/plans.json and plans.svg.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

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
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    plans = sorted(int(p) for p in args.plans.split(","))

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for steps in plans:
            label = f"{steps}-step plan"
            started = time.perf_counter()
            cfg = replace(make_config("ngs", "fast"), steps=steps, seed=args.seed)
            run = train_one(args.scan, Path(tmp), label, cfg)
            print(f"{label}: trained in {time.perf_counter() - started:.0f} s", file=sys.stderr)
            own = Infill.from_state_dict(torch.load(run / "model" / "infill.pt", weights_only=True))
            rows[label] = score(run, own)

    peer = rows[f"{plans[-1]}-step plan"]
    result = {
        "benchmark": "plans",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average": list(os.getloadavg())},
        "threads": torch.get_num_threads(),
        "scan": str(args.scan),
        "preset": "fast",
        "seed": args.seed,
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
    print(f"wrote {args.out} and {svg}")


if __name__ == "__main__":
    main()
