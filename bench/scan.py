"""Scan throughput on the simulated rig: wall time against the motion the turntable must do.

Runs the same plan twice in one process, with motion overlapped with download/write (the
default) and without (the peer), at real motion speed (time scale 1). Reports frames per minute
and how much of the capture overhead the pipelining hides.

    python bench/scan.py [--full] [--size 320x240]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from sim.rig import build_sim_rig, make_stone
from station.capture.plan import ScanPlan, default_elevations
from station.capture.session import ScanSession, SessionConfig
from station.rig_geometry import RigGeometry
from station.scanfolder import ScanFolder, atomic_write_json
from station.turntable.grbl import TurntableConfig
from station.turntable.planning import trapezoid_seconds
from machine import describe


def motion_seconds(plan: ScanPlan, config: TurntableConfig) -> float:
    """Sum of rest-to-rest move times the plan needs (shortest rotation), from the board's rates."""
    total, turn, tilt = 0.0, 0.0, 0.0
    for frame in plan.frames():
        d_turn = abs((frame.azimuth_deg - turn + 180.0) % 360.0 - 180.0)
        d_tilt = abs(frame.elevation_deg - tilt)
        moves = [
            trapezoid_seconds(d_turn, config.max_rate_deg_min[0], config.accel_deg_s2[0]) if d_turn else 0.0,
            trapezoid_seconds(d_tilt, config.max_rate_deg_min[1], config.accel_deg_s2[1]) if d_tilt else 0.0,
        ]
        total += max(moves)  # both axes move in one G1 line; the slower one sets the time
        turn, tilt = frame.azimuth_deg, frame.elevation_deg
    return total


def run_once(plan: ScanPlan, rig: RigGeometry, overlap: bool) -> float:
    with tempfile.TemporaryDirectory() as tmp, build_sim_rig(make_stone(None), rig, time_scale=1.0) as sim_rig:
        session = ScanSession(
            ScanFolder(Path(tmp) / "scan"), plan, rig, sim_rig.turntable, sim_rig.camera, sim_rig.operator,
            "bench", SessionConfig(overlap_motion=overlap),
        )
        started = time.perf_counter()
        session.run()
        return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--full", action="store_true", help="the whole 6x40 plan (default: 2x40)")
    parser.add_argument("--size", default="320x240")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    rig = RigGeometry().scaled(width, height)
    plan = ScanPlan(elevations_deg=default_elevations(6 if args.full else 2), azimuths=40)
    frames = len(plan.frames())
    motion = motion_seconds(plan, TurntableConfig())
    exposure = frames * (plan.exposure_s + 0.02)  # the sim camera's latency + exposure per frame

    rows = []
    for overlap in (True, False):
        wall = run_once(plan, rig, overlap)
        rows.append({
            "mode": "overlapped" if overlap else "sequential (peer)",
            "frames": frames,
            "wall_s": round(wall, 2),
            "motion_s": round(motion, 2),
            "exposure_s": round(exposure, 2),
            "overhead_s": round(wall - motion - exposure, 2),
            "frames_per_min": round(60.0 * frames / wall, 1),
        })
    hidden = rows[1]["wall_s"] - rows[0]["wall_s"]
    result = {
        "benchmark": "scan",
        "machine": describe(),
        "threads": 1,
        "size": [width, height],
        "plan": plan.to_dict(),
        "configs": rows,
        "overlap_hides_s": round(hidden, 2),
        "speedup_vs_sequential": round(rows[1]["wall_s"] / rows[0]["wall_s"], 3),
    }
    table = Table(title=f"simulated scan, {frames} frames at {width}x{height}, real motion speed")
    for column in rows[0]:
        table.add_column(column)
    for row in rows:
        table.add_row(*(str(v) for v in row.values()))
    Console().print(table)
    Console().print(f"overlap hides {hidden:.1f} s; speed-up {result['speedup_vs_sequential']}x against sequential")
    atomic_write_json(Path(__file__).parent / "results" / "scan.json", result)


if __name__ == "__main__":
    main()
