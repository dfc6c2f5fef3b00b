"""The runner in-process: budgets, operator cancel, fencing, and the guards that keep one scan from stalling the night.

Each test queues a copy of one tiny simulated scan and runs the real runner with the local
executor; what each test checks happens early, so only the cancel test reaches training.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from station.batch.executors import LocalExecutor
from station.batch.runner import DEFAULT_BUDGETS, BatchSettings, StageBudget, run_batch, run_job
from station.batch.stages import STAGES, read_record, scan_stage_key
from station.batch.store import Job, JobStore, StoreConfig
from station.ngs.preset_names import METHODS, PRESET_NAMES, safer_preset
from station.ngs.presets import PRESETS, make_config
from station.process.images_io import read_png16
from station.scanfolder import ScanFolder

FAST_STORE = StoreConfig(lease_seconds=2, max_attempts=3, backoff_seconds=0)
SETTINGS = BatchSettings(preset="tiny", poll_seconds=0.1)


@pytest.fixture(scope="module")
def shot(tiny_shot) -> Path:
    return tiny_shot("6")


@pytest.fixture
def queued(shot, tmp_path) -> tuple[JobStore, Path]:
    scan = Path(shutil.copytree(shot, tmp_path / "stone"))
    store = JobStore(tmp_path / "queue.sqlite", FAST_STORE)
    store.add(scan)
    return store, scan


def test_a_stage_over_its_time_budget_is_killed_and_the_scan_parked(queued):
    store, scan = queued
    budgets = {**DEFAULT_BUDGETS, "process": StageBudget(seconds=0.5, free_mb=0)}
    run_batch(store, replace(SETTINGS, budgets=budgets), LocalExecutor())
    job = store.get(scan)
    assert (job.state, job.stage, job.reason) == ("parked", "process", "process: process ran over its time budget of 0.5 s")
    assert not ScanFolder(scan).is_done("process")


def test_a_scan_without_a_finished_capture_is_parked_untouched(queued):
    store, scan = queued
    ScanFolder(scan).clear_done("capture")
    run_batch(store, SETTINGS, LocalExecutor())
    job = store.get(scan)
    assert job.state == "parked" and "no finished capture" in job.reason and "station scan" in job.reason
    assert store.stage_events(job.id) == []


def test_a_stage_the_runner_keeps_dying_in_is_parked_instead_of_looping_all_night(queued):
    store, scan = queued
    job = store.get(scan)
    key = scan_stage_key(ScanFolder(scan), STAGES[0], {}, {})
    for _ in range(SETTINGS.max_lost_starts):  # as a runner killed each time inside `process` leaves the log
        store.log_stage(job.id, "process", key, "started")
    run_batch(store, SETTINGS, LocalExecutor())
    parked = store.get(scan)
    assert parked.state == "parked" and parked.reason.startswith("process: started 10 times without an outcome")


def _events(store: JobStore, scan: Path) -> list[tuple[str, str]]:
    return [(e["stage"], e["event"]) for e in store.stage_events(store.get(scan).id)]


def test_cancelling_a_running_scan_stops_its_stage_at_the_next_heartbeat(queued):
    store, scan = queued
    runner = threading.Thread(target=run_batch, args=(store, SETTINGS, LocalExecutor()))
    runner.start()
    deadline = time.monotonic() + 60
    # the stage's own "started", not the job's stage: a cancel between the two never starts training
    while ("train", "started") not in _events(store, scan) and time.monotonic() < deadline:
        time.sleep(0.05)
    store.cancel(scan)
    runner.join(30)
    assert not runner.is_alive()
    job = store.get(scan)
    assert job.state == "cancelled"
    assert _events(store, scan) == [("process", "started"), ("process", "finished"), ("train", "started"),
                                    ("train", "abandoned")]
    assert not ScanFolder(scan).is_done("train")


def test_the_safer_preset_halves_step_sizes_gaussian_budget_and_resolution():
    base, safe = make_config("ngs", "fast"), make_config("ngs", safer_preset("fast"))
    assert safer_preset("fast") == "fast-safe" and safer_preset("fast-safe") == "fast-safe"
    assert (safe.lr_means, safe.lr_opacities) == (base.lr_means / 2, base.lr_opacities / 2)
    assert (safe.densify.max_gaussians, safe.downscale) == (base.densify.max_gaussians // 2, base.downscale * 2)
    assert (safe.steps, safe.ngs) == (base.steps, base.ngs)


def test_the_preset_names_the_runner_checks_without_torch_are_the_presets_there_are():
    assert tuple(PRESETS) == PRESET_NAMES
    for method in METHODS:
        for preset in PRESET_NAMES:
            assert make_config(method, safer_preset(preset)).method == method


def test_a_stage_process_finds_what_training_imports_to_build_its_optimizers_already_in_its_forkserver():
    """torch.optim imports torch._dynamo on building an optimizer: 2-3 s that each training stage paid."""
    code = ("import sys, torch; from station.batch.executors import PRELOAD; "
            "[__import__(m) for m in PRELOAD if m.startswith('torch')]; "  # the station modules there only add to it
            "before = set(sys.modules); torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], fused=True); "
            "print(sorted(set(sys.modules) - before))")
    built = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert built.returncode == 0, built.stderr[-2000:]
    assert built.stdout.strip() == "[]"


def test_the_stage_processes_preload_leaves_colour_science_to_the_scans_with_a_chart():
    """Every stage process forks from the preload; only a chart fit needs colour-science."""
    code = ("import sys; from station.batch.executors import PRELOAD; "
            "[__import__(m) for m in PRELOAD if m.startswith('station')]; print('colour' in sys.modules)")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert loaded.returncode == 0, loaded.stderr[-2000:]
    assert loaded.stdout.strip() == "False", "the preload imports colour-science"


def test_the_training_width_reaches_the_process_stage_as_a_parameter_of_its_run(queued):
    store, scan = queued
    # training is not under test: a free-space budget no disk meets parks the scan before it starts
    budgets = {**DEFAULT_BUDGETS, "train": StageBudget(seconds=DEFAULT_BUDGETS["train"].seconds, free_mb=1e12)}
    run_batch(store, replace(SETTINGS, training_width=80, budgets=budgets), LocalExecutor())

    images = sorted(ScanFolder(scan).images_dir.glob("*.png"))
    assert images and all(read_png16(path).shape[1] == 80 for path in images)  # the sensor is 160 wide
    job = store.get(scan)
    assert (job.state, job.stage) == ("parked", "train")
    started = [json.loads(e["detail"]) for e in store.stage_events(job.id) if (e["stage"], e["event"]) == ("process", "started")]
    assert started and all(detail["training_width"] == 80 for detail in started)  # the params its key is made from


class Clock:
    """The store's clock: real time, plus however far a test moves it on."""

    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return time.time() + self.offset


class StallsAfterTheStage:
    """The real local executor; then its runner stalls past the lease and runner B takes the job over.

    The stall is the store's own clock moving past the lease, and B's claim goes through the
    store's API: what a SIGSTOP between a stage's end and its DONE record does to runner A."""

    def __init__(self, store: JobStore, clock: Clock):
        self.store, self.clock, self.inner = store, clock, LocalExecutor()
        self.taken_over: Job | None = None

    def run(self, call, cancel, attempt, placed):
        outcome = self.inner.run(call, cancel, attempt, placed)
        self.clock.offset += self.store.config.lease_seconds + 1
        self.taken_over = self.store.claim("runner-B")
        return outcome

    def close(self) -> None:
        self.inner.close()


def test_a_runner_that_lost_its_lease_during_a_stage_writes_no_done_record(shot, tmp_path):
    scan = Path(shutil.copytree(shot, tmp_path / "stone"))
    clock = Clock()
    # a long lease: the heartbeat thread does not beat during the test, so only the fence check can stop A
    store = JobStore(tmp_path / "queue.sqlite", StoreConfig(lease_seconds=60, backoff_seconds=0), clock=clock)
    store.add(scan)
    job = store.claim("runner-A")
    executor = StallsAfterTheStage(store, clock)
    run_job(store, job, "runner-A", executor, SETTINGS, threading.Event())
    executor.close()

    assert executor.taken_over is not None and executor.taken_over.fence == job.fence + 1
    assert read_record(ScanFolder(scan), "process")["state"] == "started"  # no DONE record from runner A
    log = [(e["stage"], e["event"], json.loads(e["detail"]).get("why")) for e in store.stage_events(job.id)]
    assert log == [("process", "started", None), ("process", "abandoned", "lease lost")]
    assert store.get(scan).lease_owner == "runner-B"  # A released nothing of B's
