"""Batch throughput on one machine: scans per hour with 1 and 2 workers, and the scheduler's cost per stage.

Shoots a few tiny simulated scans once, then runs the same batch three times in this run, as an
operator would (`station batch run`, a fresh runner each time): 1 worker with all cores per stage
(the default for one worker), 1 worker with 1 thread (the peer) and 2 workers with 1 thread each.
Every stage runs for real (tiny preset). The scheduler's overhead per stage is the stage's wall
time as the runner saw it minus the time inside the stage function: keys and input hashing,
stale-output cleaning, the DONE record, the stage process's start and the output hashes (the
median over the run; the very first stage also pays for starting the stage-process server, which
is reported apart as the runner's start).

    python bench/batch.py [--scans 4] [--preset tiny]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from station.batch.stages import STAGE_NAMES
from station.batch.store import JobStore
from station.cli_scan import run_sim_scan
from station.scanfolder import atomic_write_json

SIZE = (160, 120)


def run_batch(scans: list[Path], workdir: Path, workers: int, threads: int, preset: str) -> dict:
    """Queue copies of `scans` and time one `station batch run` over them."""
    copies = [Path(shutil.copytree(scan, workdir / scan.name)) for scan in scans]
    queue = workdir / "queue.sqlite"
    store = JobStore(queue)
    for scan in copies:
        store.add(scan)
    command = [sys.executable, "-m", "station.cli_batch", "run", "--workers", str(workers), "--threads", str(threads),
               "--preset", preset, "--poll", "0.2", "--queue", str(queue)]
    started = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - started
    jobs = store.jobs()
    if any(job.state != "done" for job in jobs):
        raise SystemExit(f"batch with {workers} worker(s) did not finish:\n{result.stderr[-3000:]}")
    overhead: dict[str, list[float]] = {stage: [] for stage in STAGE_NAMES}
    inside: dict[str, list[float]] = {stage: [] for stage in STAGE_NAMES}
    finished = sorted((e["at"], e["stage"], json.loads(e["detail"])) for job in jobs
                      for e in store.stage_events(job.id) if e["event"] == "finished")
    for _, stage, detail in finished[1:]:
        overhead[stage].append(detail["wall"] - detail["seconds"])
        inside[stage].append(detail["seconds"])
    _, first_stage, first = finished[0]  # its overhead includes starting the forkserver (imports)
    inside[first_stage].append(first["seconds"])
    return {
        "workers": workers,
        "threads_per_stage": threads,
        "scans": len(scans),
        "wall_s": round(wall, 2),
        "scans_per_hour": round(3600 * len(scans) / wall, 1),
        "stage_s": {stage: round(statistics.mean(v), 2) for stage, v in inside.items()},
        "overhead_per_stage_s": {stage: round(statistics.median(v), 3) for stage, v in overhead.items()},
        "overhead_median_s": round(statistics.median(x for v in overhead.values() for x in v), 3),
        "runner_start_s": round(first["wall"] - first["seconds"], 2),
        "verdicts": sorted(str(job.verdict) for job in jobs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scans", type=int, default=4)
    parser.add_argument("--preset", default="tiny")
    args = parser.parse_args()
    load_at_start = os.getloadavg()[0]  # other work on the machine takes cores from the batch: say how much
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        shot = [root / "shot" / f"stone{k}" for k in range(args.scans)]
        for k, scan in enumerate(shot):
            run_sim_scan(scan, str(k + 1), 2, 8, SIZE, 0.01, lambda done, total, what: None)
        cores = os.cpu_count() or 1
        configs = [(1, cores), (1, 1), (2, max(1, cores // 2))]
        rows = [run_batch(shot, root / f"w{w}t{t}", w, t, args.preset) for w, t in configs]
    default, peer, two = rows
    result = {
        "benchmark": "batch",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0],
                    "load_avg_1min": {"start": round(load_at_start, 2), "end": round(os.getloadavg()[0], 2)}},
        "threads": {f"{w} worker(s) x {t} thread(s)": t for w, t in configs},
        "scan": {"elevations": 2, "azimuths": 8, "size": list(SIZE), "preset": args.preset},
        "configs": rows,
        "peer": f"1 worker x {peer['threads_per_stage']} thread(s), same scans, same run",
        "speedup_2_vs_1": round(peer["wall_s"] / two["wall_s"], 3),
        "speedup_2_vs_1_all_cores": round(default["wall_s"] / two["wall_s"], 3),
    }
    table = Table(title=f"station batch, {args.scans} tiny scans ({SIZE[0]}x{SIZE[1]}, 2x8 views, preset {args.preset})")
    stages = " / ".join(STAGE_NAMES)
    for column in ("workers", "threads", "wall s", "scans/hour", f"in stage s ({stages})", f"overhead s ({stages})",
                   "runner start s"):
        table.add_column(column)
    for row in rows:
        table.add_row(str(row["workers"]), str(row["threads_per_stage"]), str(row["wall_s"]), str(row["scans_per_hour"]),
                      " / ".join(str(row["stage_s"][s]) for s in STAGE_NAMES),
                      " / ".join(str(row["overhead_per_stage_s"][s]) for s in STAGE_NAMES), str(row["runner_start_s"]))
    Console().print(table)
    Console().print(f"2 workers against 1 worker x 1 thread (the peer): {result['speedup_2_vs_1']}x the throughput; "
                    f"against 1 worker x {cores} threads: {result['speedup_2_vs_1_all_cores']}x")
    atomic_write_json(Path(__file__).parent / "results" / "batch.json", result)


if __name__ == "__main__":
    main()
