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

`--nodes 1,2,3` measures the Ray executor instead: scans per hour on a Ray cluster of that many
single-CPU nodes, all on this machine (`ray.cluster_utils.Cluster`, token auth on, one runner
slot per node), and adds a projection on paper of one night's work (40 scans at the default
preset) against nodes and GPUs, from the stage times of a default scan in the other benches'
JSON. Written to bench/results/batch_ray_nodes.json.

    python bench/batch.py --nodes 1,2,3 [--scans 3] [--preset tiny]
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
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
from machine import describe

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


def shoot(root: Path, scans: int) -> list[Path]:
    shot = [root / "shot" / f"stone{k}" for k in range(scans)]
    for k, scan in enumerate(shot):
        run_sim_scan(scan, str(k + 1), 2, 8, SIZE, 0.01, lambda done, total, what: None)
    return shot


def run_on_cluster(scans: list[Path], workdir: Path, nodes: int, preset: str) -> dict:
    """A fresh Ray cluster of `nodes` 1-CPU nodes on this machine, one runner slot per node, one timed batch."""
    from ray._raylet import AuthenticationTokenLoader, Config
    from ray.cluster_utils import Cluster

    temp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")  # Ray's unix sockets: a short path
    env = {"RAY_TMPDIR": temp, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    os.environ.update(env)
    Config.initialize("")  # this process reads the auth mode and token again, as Ray's own set-up does
    AuthenticationTokenLoader.instance().reset_cache()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        for _ in range(nodes - 1):
            cluster.add_node(num_cpus=1)
        copies = [Path(shutil.copytree(scan, workdir / scan.name)) for scan in scans]
        queue = workdir / "queue.sqlite"
        store = JobStore(queue)
        for scan in copies:
            store.add(scan)
        command = [sys.executable, "-m", "station.cli_batch", "run", "--executor", "ray", "--ray-address",
                   cluster.address, "--workers", str(nodes), "--threads", "1", "--preset", preset, "--poll", "0.2",
                   "--queue", str(queue)]
        load = os.getloadavg()[0]
        started = time.perf_counter()
        result = subprocess.run(command, capture_output=True, text=True)
        wall = time.perf_counter() - started
    finally:
        cluster.shutdown()
        shutil.rmtree(temp, ignore_errors=True)
    jobs = store.jobs()
    if any(job.state != "done" for job in jobs):
        raise SystemExit(f"batch on {nodes} node(s) did not finish:\n{result.stderr[-3000:]}")
    finished = [(e["stage"], json.loads(e["detail"])) for job in jobs for e in store.stage_events(job.id)
                if e["event"] == "finished"]
    return {
        "nodes": nodes,
        "scans": len(scans),
        "wall_s": round(wall, 2),
        "scans_per_hour": round(3600 * len(scans) / wall, 1),
        "stage_s": {stage: round(statistics.mean(d["seconds"] for s, d in finished if s == stage), 2)
                    for stage in STAGE_NAMES},
        "nodes_used": len({d["node"] for _, d in finished}),
        "load_avg_1min": {"start": round(load, 2), "end": round(os.getloadavg()[0], 2)},
        "verdicts": sorted(str(job.verdict) for job in jobs),
    }


def default_scan_stage_times() -> dict:
    """Stage times of a default scan (6x40, preset fast, 2 threads on this machine) from the other benches' JSON."""
    results = Path(__file__).parent / "results"
    process = json.loads((results / "process.json").read_text())["posing"]
    ngs = json.loads((results / "ngs_presets.json").read_text())
    mesh = json.loads((results / "mesh.json").read_text())
    rig_240 = next(r["seconds"] for r in process["rows"] if r["views"] == 240 and r["method"] == "rig")
    return {
        "process_s": round(process["scan"]["develop_and_mask_s"] + rig_240, 1),
        "train_s": ngs["methods"]["ngs"]["train_seconds"],
        "export_s": round(mesh["methods"]["opacity"]["seconds"], 1),
        "sources": {
            "process_s": "process.json: develop and mask of a 6x40 scan at 480x360, plus posing 240 views (rig)",
            "train_s": f"ngs_presets.json: NGS, preset fast, {ngs['scan']}, {ngs['threads']} threads",
            "export_s": "mesh.json: the opacity mesh alone (splat writing and the gate not included: a lower bound)",
        },
    }


def projection(times: dict, scans: int, gpu_speedup: float) -> list[dict]:
    """Hours for `scans` scans against CPU nodes and GPU nodes, on paper.

    Each node (this machine: 2 cores) runs one stage at a time, stages spread evenly, no waiting
    on a stage of the same scan; training on a GPU node takes train_s / gpu_speedup."""
    cpu_work = times["process_s"] + times["export_s"]
    rows = []
    for gpus in (0, 1, 2):
        for nodes in (1, 2, 4, 8):
            if gpus > nodes:
                continue
            if gpus == 0:
                hours = scans * (cpu_work + times["train_s"]) / nodes / 3600
            else:  # training on the GPU nodes; the rest fills every node's remaining time
                train_h = scans * times["train_s"] / gpu_speedup / gpus / 3600
                hours = max(train_h, (scans * (cpu_work + times["train_s"] / gpu_speedup)) / nodes / 3600)
            rows.append({"nodes": nodes, "gpu_nodes": gpus, "hours": round(hours, 2)})
    return rows


def bench_nodes(counts: list[int], scans: int, preset: str, night_scans: int = 40, gpu_speedup: float = 10.0) -> None:
    load_at_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        shot = shoot(root, scans)
        rows = [run_on_cluster(shot, root / f"n{n}", n, preset) for n in counts]
    times = default_scan_stage_times()
    result = {
        "benchmark": "batch_ray_nodes",
        "machine": {**describe(),
                    "load_avg_1min": {"start": round(load_at_start, 2), "end": round(os.getloadavg()[0], 2)},
                    "note": f"every node runs on this one {os.cpu_count()}-core machine, shared with other work: "
                            "more nodes than cores cannot add throughput here"},
        "ray": __import__("ray").__version__,
        "scan": {"elevations": 2, "azimuths": 8, "size": list(SIZE), "preset": preset},
        "configs": rows,
        "night": {"scans": night_scans, "preset": "fast (the batch default)", "stage_times": times,
                  "gpu_speedup_assumed": gpu_speedup,
                  "gpu_note": "not measured: this machine has no GPU, and the trainer runs on the CPU today",
                  "hours": projection(times, night_scans, gpu_speedup)},
    }
    table = Table(title=f"station batch on Ray, {scans} tiny scans, 1-CPU nodes on one {os.cpu_count()}-core machine")
    for column in ("nodes", "wall s", "scans/hour", "in stage s (" + " / ".join(STAGE_NAMES) + ")", "nodes used",
                   "load (1 min) start / end"):
        table.add_column(column)
    for row in rows:
        table.add_row(str(row["nodes"]), str(row["wall_s"]), str(row["scans_per_hour"]),
                      " / ".join(str(row["stage_s"][s]) for s in STAGE_NAMES), str(row["nodes_used"]),
                      f"{row['load_avg_1min']['start']} / {row['load_avg_1min']['end']}")
    night = Table(title=f"on paper: {night_scans} default scans (process {times['process_s']} s, train "
                        f"{times['train_s']} s, export {times['export_s']} s a scan; GPU {gpu_speedup:g}x assumed)")
    for column in ("nodes (2 cores each)", "of them GPU", "hours"):
        night.add_column(column)
    for row in result["night"]["hours"]:
        night.add_row(str(row["nodes"]), str(row["gpu_nodes"]), str(row["hours"]))
    Console().print(table)
    Console().print(night)
    atomic_write_json(Path(__file__).parent / "results" / "batch_ray_nodes.json", result)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scans", type=int, default=4)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--nodes", help="comma-separated node counts: measure the Ray executor on that many 1-CPU nodes")
    args = parser.parse_args()
    if args.nodes:
        bench_nodes([int(n) for n in args.nodes.split(",")], args.scans, args.preset)
        return
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
        "machine": {**describe(),
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
