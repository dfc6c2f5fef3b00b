"""A training step inside a batch stage process, under each way of sizing its thread pools.

A batch stage runs in a process forked from the local executor's forkserver, which has imported
torch. There `stage_run.limit_threads` sizes numba's and torch's pools; the peer is the way it did
before: numba's workqueue threading layer, chosen because numba's OpenMP pool, started after torch's
count was set, resets that count to all cores. Each configuration runs in its own stage-like process,
in turns, `--rounds` times, and times `bench/raster.py`'s step (20k Gaussians, 256², SH3): median and
mean, since a training run pays the mean. The threading layer and torch's thread count are reported as
the step saw them. No error axis: both compute the same step.

    python bench/thread_pools.py [--gaussians 20000] [--size 256] [--repeats 60] [--rounds 3]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table

from station.batch.executors import PRELOAD
from station.scanfolder import atomic_write_json
from machine import describe

BENCH = Path(__file__).resolve().parent


def _peer_limit_threads(threads: int) -> None:
    """The earlier `limit_threads`: workqueue layer, torch's count first."""
    import numba
    import torch

    numba.config.THREADING_LAYER = "workqueue"
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def _time_step(way: str, threads: int, gaussians: int, size: int, repeats: int, result) -> None:
    """In a stage-like process: size the pools `way`, then send the bench step's median and mean ms."""
    import numba
    import torch

    from station.batch.stage_run import limit_threads

    (limit_threads if way == "limit_threads" else _peer_limit_threads)(threads)
    sys.path.insert(0, str(BENCH))
    from raster import step_walls

    walls, _ = step_walls(gaussians, size, repeats)
    result.send({"way": way, "threads": threads, "layer": numba.threading_layer(),
                 "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
                 "step_ms": round(1e3 * sorted(walls)[len(walls) // 2], 2),
                 "mean_step_ms": round(1e3 * sum(walls) / len(walls), 2), "load_1min": round(os.getloadavg()[0], 2)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=20_000)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=BENCH / "results" / "thread_pools.json")
    args = parser.parse_args()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    settings = [(way, threads) for threads in sorted({1, min(2, os.cpu_count() or 1), os.cpu_count() or 1})
                for way in ("limit_threads", "workqueue_peer")]
    runs: dict[tuple[str, int], list[dict]] = {setting: [] for setting in settings}
    for _ in range(args.rounds):  # in turns, so every setting sees the same machine
        for way, threads in settings:
            receive, send = context.Pipe(duplex=False)
            process = context.Process(target=_time_step, args=(way, threads, args.gaussians, args.size, args.repeats,
                                                               send))
            process.start()
            send.close()
            runs[way, threads].append(receive.recv())
            process.join()
    configs = []
    for setting, rounds in runs.items():
        config = dict(rounds[0])
        for key in ("step_ms", "mean_step_ms", "load_1min"):
            config[key] = statistics.median(r[key] for r in rounds)
        config["rounds"] = [{key: r[key] for key in ("step_ms", "mean_step_ms")} for r in rounds]
        configs.append(config)
    for c in configs:
        peer = next(p for p in configs if p["threads"] == c["threads"] and p["way"] == "workqueue_peer")
        c["ratio_vs_peer"] = round(c["step_ms"] / peer["step_ms"], 3)
        c["mean_ratio_vs_peer"] = round(c["mean_step_ms"] / peer["mean_step_ms"], 3)
    data = {"benchmark": "thread_pools", "gaussians": args.gaussians, "size": [args.size, args.size],
            "machine": describe(), "configs": configs}
    atomic_write_json(args.out, data)
    table = Table(title=f"step in a stage process, {args.gaussians} Gaussians, {args.size}²")
    for column in ("way", "threads", "layer", "torch threads", "median ms", "× peer", "mean ms", "× peer", "load"):
        table.add_column(column)
    for c in configs:
        table.add_row(c["way"], str(c["threads"]), c["layer"], str(c["torch_threads"]), f"{c['step_ms']:.2f}",
                      f"{c['ratio_vs_peer']:.2f}", f"{c['mean_step_ms']:.2f}", f"{c['mean_ratio_vs_peer']:.2f}",
                      f"{c['load_1min']:.2f}")
    Console().print(table)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
