"""Fault injection: each fault ends in its documented state with a reason, and the other scans are unaffected.

The documented states (station/batch/runner.py):
- a corrupt raw: the frame is left out, the scan finishes with the gate's verdict, and the reason names the raw;
- an unmaskable frame: flagged by process and named in the reason. On these tiny textureless stones SfM finds
  no points, so the start cloud is carved from the masks; an empty mask carves it all away and training parks
  the scan for want of points (a scan with SfM points would finish, the frame named beside its verdict);
- NaN in training (through the trainer's own check_finite guard): retried once with the safer preset, then parked;
- a full disk (the stage's free-space budget not met): parked at that stage; a retry once space is freed
  finishes only what was left.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from batch_support import TINY_RUN, batch, events, status, verify_scan
from station.scanfolder import ScanFolder, sha256_file

pytestmark = pytest.mark.slow

CORRUPT_RAW = "raw/e1_a003.dng"
EMPTY_VIEW = "raw/e1_a005.dng"
FAULT_HOOKS = Path(__file__).parent / "fault_hooks"  # its sitecustomize injects the NaN into a training run


@pytest.fixture(scope="module")
def shot(tiny_shot) -> Path:
    return tiny_shot("5")


def corrupt_raw(scan: Path, raw: str) -> None:
    """Bit rot after capture: the raw's pixel bytes are overwritten; the manifest still has the old sha256."""
    path = scan / raw
    data = bytearray(path.read_bytes())
    data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
    path.write_bytes(bytes(data))


def shoot_an_empty_view(scan: Path, raw: str) -> None:
    """The view shows the empty plate (the stone was lifted off): a valid raw, checksummed, with nothing to mask."""
    folder = ScanFolder(scan)
    entries = folder.read_manifest()
    target = next(e for e in entries if e.file == raw)
    plate = next(e for e in entries if e.kind == "plate" and e.elevation_deg == target.elevation_deg)
    shutil.copyfile(scan / plate.file, scan / raw)
    folder.write_manifest([replace(e, sha256=sha256_file(scan / raw)) if e is target else e for e in entries])


@pytest.fixture(scope="module")
def faulty_batch(shot, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("faults")
    scans = {name: Path(shutil.copytree(shot, root / name)) for name in ("healthy", "corrupt_raw", "empty_view", "diverges")}
    corrupt_raw(scans["corrupt_raw"], CORRUPT_RAW)
    shoot_an_empty_view(scans["empty_view"], EMPTY_VIEW)
    queue = root / "queue.sqlite"
    assert batch("add", *scans.values(), "--queue", queue).returncode == 0
    nan = {"STATION_TEST_INJECT_NAN": f"5:{scans['diverges']}",
           "PYTHONPATH": os.pathsep.join([str(FAULT_HOOKS), os.environ.get("PYTHONPATH", "")])}
    result = batch("run", "--workers", "2", *TINY_RUN, "--queue", queue, "--json", env=nan)
    return {"root": root, "scans": scans, "queue": queue, "result": result, "jobs": status(queue)}


def test_a_corrupt_raw_is_left_out_and_named_in_the_reason(faulty_batch):
    job = faulty_batch["jobs"]["corrupt_raw"]
    assert job["state"] == "done", faulty_batch["result"].stderr[-3000:]
    assert CORRUPT_RAW in job["reason"] and "unreadable" in job["reason"]
    scan = faulty_batch["scans"]["corrupt_raw"]
    assert not (scan / "images" / "e1_a003.png").exists()
    assert verify_scan(scan) == [f"manifest: {CORRUPT_RAW} fails its sha256"]


def test_an_unmaskable_frame_parks_a_hull_started_scan_and_is_named_in_the_reason(faulty_batch):
    job = faulty_batch["jobs"]["empty_view"]
    assert job["state"] == "parked" and job["stage"] == "train"
    assert job["reason"].startswith("train: BadInputError: ") and "no usable points" in job["reason"]
    assert f"process flagged 1 frame: {EMPTY_VIEW} (mask: empty" in job["reason"]
    log = events(faulty_batch["queue"], faulty_batch["scans"]["empty_view"])
    assert [(e["stage"], e["event"]) for e in log if e["event"] == "failed"] == [("train", "failed")]


def test_nan_in_training_is_retried_once_with_the_safer_preset_then_parked(faulty_batch):
    job = faulty_batch["jobs"]["diverges"]
    assert job["state"] == "parked"
    assert job["reason"].startswith("train failed with preset tiny and again with tiny-safe: TrainingError: step 5")
    assert "NaN" in job["reason"]
    log = events(faulty_batch["queue"], faulty_batch["scans"]["diverges"])
    trains = [(e["event"], e["detail"].get("preset"), e["detail"].get("kind")) for e in log if e["stage"] == "train"]
    assert trains == [("started", "tiny", None), ("failed", "tiny", "diverged"),
                      ("started", "tiny-safe", None), ("failed", "tiny-safe", "diverged")]


def test_the_healthy_scan_is_unaffected(faulty_batch):
    job = faulty_batch["jobs"]["healthy"]
    assert job["state"] == "done" and job["verdict"] in ("pass", "quarantined")
    assert "process flagged" not in (job["reason"] or "")
    log = events(faulty_batch["queue"], faulty_batch["scans"]["healthy"])
    assert [e for e in log if e["event"] == "failed"] == []
    assert verify_scan(faulty_batch["scans"]["healthy"]) == []


def test_the_run_exits_1_and_its_summary_names_every_fault(faulty_batch):
    result = faulty_batch["result"]
    assert result.returncode == 1
    report = json.loads(result.stdout)
    assert report["counts"].get("parked") == 2
    page = Path(report["summary_html"]).read_text()
    for name, job in faulty_batch["jobs"].items():
        assert name in page
    assert "tiny-safe" in page and CORRUPT_RAW in page
    assert "<script" not in page and "http" not in page and "src=" not in page  # self-contained


def test_a_full_disk_parks_the_scan_and_a_retry_finishes_only_what_was_left(faulty_batch, shot):
    queue = faulty_batch["queue"]
    scan = Path(shutil.copytree(shot, faulty_batch["root"] / "disk_full"))
    assert batch("add", scan, "--queue", queue).returncode == 0
    before = status(queue)
    logs_before = {name: events(queue, path) for name, path in faulty_batch["scans"].items()}

    batch("run", *TINY_RUN, "--queue", queue, "--disk-budget", "export=1e12")
    parked = status(queue)["disk_full"]
    assert parked["state"] == "parked" and parked["reason"].startswith("export: ")
    assert "MB free" in parked["reason"]
    assert not (scan / "asset").exists()
    after = status(queue)
    assert {n: after[n] for n in faulty_batch["scans"]} == {n: before[n] for n in faulty_batch["scans"]}
    assert {name: events(queue, path) for name, path in faulty_batch["scans"].items()} == logs_before

    assert batch("retry", scan, "--queue", queue).returncode == 0
    batch("run", *TINY_RUN, "--queue", queue)
    assert status(queue)["disk_full"]["state"] == "done"
    log = events(queue, scan)
    since_retry = log[[e["event"] for e in log].index("retried") + 1:]
    assert [(e["stage"], e["event"]) for e in since_retry] == [
        ("process", "skipped"), ("train", "skipped"), ("export", "started"), ("export", "finished")]
    assert verify_scan(scan) == []
