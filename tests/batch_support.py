"""Shared by the batch tests: tiny simulated scans, the batch CLI as a subprocess, and file checks.

Everything here drives the real pipeline; nothing is mocked. A tiny scan is 2 x 8 views at
160x120 and trains with the `tiny` preset, so one scan takes about half a minute on one core.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image

from station.batch.stages import STAGES, TEMP_FILE, finished_record, read_record
from station.cli_scan import run_sim_scan
from station.export.splat_formats import read_splat
from station.process.images_io import read_exr
from station.process.transforms import read_transforms
from station.scanfolder import ScanFolder

BATCH = [sys.executable, "-m", "station.cli_batch"]  # the same commands as `station batch`
TINY_RUN = ["--preset", "tiny", "--lease", "2", "--poll", "0.2", "--backoff", "0"]


@contextlib.contextmanager
def one_ray_at_a_time() -> Iterator[None]:
    """Hold the machine's one Ray slot: two Ray instances at once on two cores (xdist workers) starve each other."""
    with open(Path(tempfile.gettempdir()) / f"station-tests-ray-{os.getuid()}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def process_ids() -> list[int]:
    return [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()]


def proc_stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command name (state first, parent second), or None once it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def shoot(out: Path, stone: str) -> Path:
    """A finished 2 x 8 scan of stone `stone` at 160x120 (plates included)."""
    run_sim_scan(out, stone, 2, 8, (160, 120), 0.01, lambda done, total, what: None)
    return out


def copy_scans(sources: list[Path], into: Path) -> list[Path]:
    into.mkdir(parents=True, exist_ok=True)
    return [Path(shutil.copytree(src, into / src.name)) for src in sources]


def batch(*args: object, env: dict[str, str] | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run `station batch ARGS` to completion."""
    return subprocess.run([*BATCH, *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def status(queue: Path) -> dict[str, dict]:
    """`station batch status --json`, keyed by scan folder name."""
    result = batch("status", "--queue", queue, "--json")
    assert result.returncode == 0, result.stderr
    return {Path(job["scan"]).name: job for job in json.loads(result.stdout)["jobs"]}


def events(queue: Path, scan: Path) -> list[dict]:
    """The job's stage log: [{"stage", "key", "event", "detail"}], details decoded."""
    from station.batch.store import JobStore

    store = JobStore(queue)
    rows = store.stage_events(store.get(scan).id)
    return [{**row, "detail": json.loads(row["detail"] or "{}")} for row in rows]


def temp_files(root: Path) -> list[Path]:
    return [Path(d) / n for d, _, names in os.walk(root) for n in names if TEMP_FILE.match(n)]


def verify_scan(root: Path) -> list[str]:
    """Problems with a finished scan folder; empty when every file verifies and reads back."""
    scan = ScanFolder(root)
    problems = [f"manifest: {e.file} fails its sha256" for e in scan.read_manifest() if not scan.verify_entry(e)]
    problems += [f"temp file left: {p}" for p in temp_files(root)]
    for spec in STAGES:
        record = read_record(scan, spec.name)
        if record is None or finished_record(scan, spec, record["key"]) is None:
            problems.append(f"{spec.name}: no done record whose outputs verify")
    for path in sorted(scan.images_dir.glob("*.png")) + sorted(scan.masks_dir.glob("*.png")):
        with Image.open(path) as image:
            image.load()
    for path in sorted(scan.images_linear_dir.glob("*.exr")):
        if not np.isfinite(read_exr(path)).all():
            problems.append(f"{path}: non-finite pixels")
    read_transforms(scan)
    for name in ("surface.pt", "infill.pt"):
        torch.load(scan.model_dir / name, weights_only=True)
    json.loads((scan.model_dir / "train_metrics.json").read_text())
    asset = scan.asset_dir
    for name in ("splat.ply", "infill.ply", "splat.splat", "splat.spz", "splat.glb"):
        read_splat(asset / name)
    for name in ("mesh.ply", "mesh.glb"):
        if len(trimesh.load_mesh(asset / name).faces) == 0:
            problems.append(f"asset/{name}: no faces")
    json.loads((asset / "gate.json").read_text()), json.loads((asset / "metrics.json").read_text())
    if not (asset / "report.html").read_text().rstrip().endswith("</html>"):
        problems.append("asset/report.html: truncated")
    return problems


def redone_stages(log: list[dict]) -> list[str]:
    """Stages started again under a key they had already finished with: work done twice."""
    finished: set[tuple[str, str]] = set()
    redone = []
    for event in log:
        key = (event["stage"], event["key"])
        if event["event"] == "started" and key in finished:
            redone.append(event["stage"])
        if event["event"] == "finished":
            finished.add(key)
    return redone
