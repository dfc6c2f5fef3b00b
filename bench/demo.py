"""`station demo` end to end, stage by stage: this tree against an earlier revision, in the same run.

Runs the demo exactly as a user does (`python -m station demo`), once per tree, each in a fresh
process with its own empty numba cache (both pay their compile), then this tree's again with the
cache it filled (as every demo after the first), and reads the stage times from the demo's own
summary lines. The error axis is the gate's: held-out PSNR and SOS, mesh watertight.

    python bench/demo.py [--against REV] [--out bench/results/demo.json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from revisions import unpack, working_tree
from machine import describe

ROOT = Path(__file__).resolve().parents[1]
STAGE_LINE = re.compile(r"^(scan|process|train|export): (\d+) s(?: \((.*)\))?$")
STEP = re.compile(r"([a-z ]+?) (\d+) s")


def stage_times(stderr: str) -> dict[str, float]:
    """{stage: seconds} from the demo's summary lines; the process stage's own steps as "process/<step>"."""
    times: dict[str, float] = {}
    for line in stderr.splitlines():
        if match := STAGE_LINE.match(line.strip()):
            times[match[1]] = float(match[2])
            for name, seconds in STEP.findall(match[3] or ""):
                times[f"process/{name.strip()}"] = float(seconds)
        elif match := re.search(r"demo finished in (\d+) s", line):
            times["total"] = float(match[1])
    return times


def stage_times_from_files(scan: Path) -> dict[str, float]:
    """The stage times a demo that printed none (an older revision) left in its scan folder: each stage's own
    clock, so the gaps between stages are not in them."""
    def read(relative: str) -> dict:
        path = scan / relative
        return json.loads(path.read_text()) if path.is_file() else {}

    process, train, export = read("stages/process.json"), read("model/train_metrics.json"), read("stages/export.json")
    steps = {"process/develop": process.get("develop", {}).get("seconds"),
             "process/poses": process.get("poses", {}).get("seconds"),
             "process/masks across rings": process.get("masks_across_rings", {}).get("seconds"),
             "train": train.get("report", {}).get("seconds"), "export": export.get("seconds")}
    return {name: round(float(seconds), 1) for name, seconds in steps.items() if isinstance(seconds, (int, float))}


def run_demo(tree: Path, work: Path, cache: Path) -> dict:
    """One `station demo` from `tree`'s source with numba's cache in `cache`; its stage times, verdict and load."""
    env = {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    load_before = os.getloadavg()
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "station", "demo", "--out", str(work / "demo"), "--json"],
                          cwd=tree, env=env, capture_output=True, text=True)
    wall = time.monotonic() - started
    verdict = json.loads(done.stdout) if done.stdout.strip().startswith("{") else {}
    gate = {c["name"]: c["value"] for c in verdict.get("gate", {}).get("checks", [])}
    times = stage_times(done.stderr)
    return {"exit": done.returncode, "wall_s": round(wall, 1),
            "stages_s": times if "train" in times else times | stage_times_from_files(work / "demo" / "scan"),
            "gate_passed": verdict.get("pass"), "gate": gate, **steps_trained(work / "demo" / "scan"),
            "load_1min_before": round(load_before[0], 2), "load_1min_after": round(os.getloadavg()[0], 2)}


def steps_trained(scan: Path) -> dict[str, int]:
    """The steps the demo trained and the steps its plan had (an early finish or an extension tells them apart)."""
    metrics = scan / "model" / "train_metrics.json"
    if not metrics.is_file():
        return {}
    train = json.loads(metrics.read_text())
    return {"train_steps": train["report"]["steps"], "planned_steps": train["planned_steps"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--against", metavar="REV", help="also run git revision REV's demo first (the peer)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "demo.json")
    args = parser.parse_args()
    runs = {}
    with tempfile.TemporaryDirectory(prefix="demo-bench-") as tmp:
        if args.against:
            old = Path(tmp) / "before-tree"
            old.mkdir()
            before = unpack(args.against, old)
            runs["before"] = run_demo(old, Path(tmp) / "before", Path(tmp) / "before-cache") | {
                "revision": before, "numba_cache": "empty"}
        cache, revision = Path(tmp) / "after-cache", working_tree()
        runs["after"] = run_demo(ROOT, Path(tmp) / "after", cache) | {"revision": revision, "numba_cache": "empty"}
        runs["after, warm"] = run_demo(ROOT, Path(tmp) / "after-warm", cache) | {
            "revision": revision, "numba_cache": "kept from the run before"}
    result = {"benchmark": "demo", "machine": describe(),
              "note": "before and after start with an empty numba cache, so both include their kernels' compile "
                      "time; 'after, warm' runs again with the cache the after run filled, as a second demo does",
              "runs": runs}
    if "before" in runs and runs["before"]["stages_s"].get("total") and runs["after"]["stages_s"].get("total"):
        result["total_ratio_after_over_before"] = round(runs["after"]["stages_s"]["total"]
                                                        / runs["before"]["stages_s"]["total"], 3)
    names = sorted({k for run in runs.values() for k in run["stages_s"]}, key=_stage_order)
    table = Table(title="station demo, seconds by stage (the demo's own summary)")
    table.add_column("stage")
    for name in runs:
        table.add_column(f"{name} ({runs[name]['revision']})")
    for stage in names:
        table.add_row(stage, *(str(run["stages_s"].get(stage, "")) for run in runs.values()))
    table.add_row("steps trained (planned)", *(f"{run.get('train_steps', '')} ({run.get('planned_steps', '')})"
                                               for run in runs.values()))
    for key in ("PSNR", "SOS"):
        table.add_row(key, *(str(round(run["gate"].get(key) or 0, 3)) for run in runs.values()))
    table.add_row("gate passed", *(str(run["gate_passed"]) for run in runs.values()))
    table.add_row("load before/after", *(f"{run['load_1min_before']}/{run['load_1min_after']}" for run in runs.values()))
    Console().print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


def _stage_order(name: str) -> tuple[int, str]:
    order = ["scan", "process", "process/develop", "process/poses", "process/masks across rings", "train", "export",
             "total"]
    return (order.index(name) if name in order else len(order), name)


if __name__ == "__main__":
    main()
