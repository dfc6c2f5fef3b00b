"""How long OpenMP's idle threads should spin before they sleep (GOMP_SPINCOUNT), quiet and under load.

`station/__init__.py` sets OMP_WAIT_POLICY=PASSIVE: torch and numba each bring a libgomp pool, and a pool
that spins steals the cores from the other. Passive threads sleep at once, so every parallel region pays a
wake-up; a short spin saves it where the cores are free. The peer is the passive default (spin count 0).
Each setting times `bench/raster.py`'s training step in a fresh process (libgomp reads the variable once, at
load), in turns, quiet and then beside one busy loop per core that this bench starts and stops. No error axis:
every setting computes the same step.

    python bench/spin_count.py [--spins 0,3000,20000] [--gaussians 20000] [--size 256] [--rounds 4]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from machine import describe, summary

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path.insert(0, str(ROOT))
from station.scanfolder import atomic_write_json  # noqa: E402

TIMER = """
import json, sys
sys.path.insert(0, {bench!r})
from raster import step_walls
from station.ngs.raster import set_num_threads
set_num_threads(2)
walls, cpu_s = step_walls({gaussians}, {size}, {repeats})
print(json.dumps({{"walls": walls, "cpu_s": cpu_s}}))
"""


def _busy() -> None:
    while True:
        pass


def _time(spin: int, args: argparse.Namespace) -> dict:
    """One fresh process timing the step at this spin count -> median and mean ms, CPU ms a step."""
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", GOMP_SPINCOUNT=str(spin), PYTHONPATH=str(ROOT))
    code = TIMER.format(bench=str(BENCH), gaussians=args.gaussians, size=args.size, repeats=args.repeats)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    run = json.loads(out.splitlines()[-1])
    walls = run["walls"]
    return {"step_ms": 1e3 * statistics.median(walls), "mean_step_ms": 1e3 * statistics.fmean(walls),
            "cpu_ms": 1e3 * run["cpu_s"] / len(walls)}


def _measure(spins: list[int], args: argparse.Namespace, loaded: bool) -> list[dict]:
    hogs = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(os.cpu_count() or 1)] if loaded else []
    for hog in hogs:
        hog.start()
    try:
        runs: dict[int, list[dict]] = {spin: [] for spin in spins}
        for turn in range(args.rounds):  # in turns, each order as often, so every setting sees the same machine
            for spin in (spins if turn % 2 == 0 else spins[::-1]):
                runs[spin].append(_time(spin, args) | {"load_1min": os.getloadavg()[0]})
    finally:
        for hog in hogs:
            hog.terminate()
            hog.join()
    rows = []
    for spin, rounds in runs.items():
        row = {"spin_count": spin, "loaded": loaded,
               **{key: round(statistics.median(r[key] for r in rounds), 2)
                  for key in ("step_ms", "mean_step_ms", "cpu_ms", "load_1min")},
               "rounds": [{key: round(r[key], 2) for key in ("step_ms", "mean_step_ms", "cpu_ms")} for r in rounds]}
        rows.append(row)
    peer = next(r for r in rows if r["spin_count"] == 0)
    for row in rows:
        row["ratio_vs_passive"] = round(row["step_ms"] / peer["step_ms"], 3)
        row["mean_ratio_vs_passive"] = round(row["mean_step_ms"] / peer["mean_step_ms"], 3)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spins", default="0,3000,20000", help="comma-separated GOMP_SPINCOUNT values; 0 is the peer")
    parser.add_argument("--gaussians", type=int, default=20_000)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--out", type=Path, default=BENCH / "results" / "spin_count.json")
    args = parser.parse_args()
    spins = sorted({0, *(int(s) for s in args.spins.split(","))})
    started = time.perf_counter()
    rows = _measure(spins, args, loaded=False) + _measure(spins, args, loaded=True)
    data = {"benchmark": "spin_count", "gaussians": args.gaussians, "size": [args.size, args.size],
            "threads": 2, "repeats": args.repeats, "rounds": args.rounds, "machine": describe(),
            "load": f"quiet, then one busy loop per core ({os.cpu_count()})", "configs": rows,
            "seconds": round(time.perf_counter() - started, 1)}
    atomic_write_json(args.out, data)
    table = Table(title=f"training step, {args.gaussians} Gaussians, {args.size}², 2 threads: "
                        f"{summary(data['machine'])}")
    for column in ("machine", "GOMP_SPINCOUNT", "median ms", "× passive", "mean ms", "× passive", "CPU ms", "load"):
        table.add_column(column)
    for r in rows:
        table.add_row("loaded" if r["loaded"] else "quiet", str(r["spin_count"]), f"{r['step_ms']:.2f}",
                      f"{r['ratio_vs_passive']:.2f}", f"{r['mean_step_ms']:.2f}", f"{r['mean_ratio_vs_passive']:.2f}",
                      f"{r['cpu_ms']:.1f}", f"{r['load_1min']:.2f}")
    Console().print(table)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
