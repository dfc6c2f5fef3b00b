"""A stalled runner (SIGSTOP, a frozen VM) loses its scan to another runner, and its stage stops itself.

Its own module, apart from the chaos run in test_batch_chaos.py: it shares nothing with that run, and
under xdist a module stays on one worker, so the two run side by side.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from batch_support import BATCH, batch, copy_scans, events, proc_stat, process_ids, redone_stages, verify_scan
from station.batch.store import JobStore

pytestmark = pytest.mark.slow

FAULT_HOOKS = Path(__file__).parent / "fault_hooks"
STEP_SLEEP = 0.05  # runner A's 300 tiny steps then last over 15 s, well past its 3 s lease on any machine


def _descendants(pid: int) -> set[int]:
    """Every live process below `pid`, from /proc."""
    parents: dict[int, list[int]] = {}
    for child in process_ids():
        if (fields := proc_stat(child)) is not None:
            parents.setdefault(int(fields[1]), []).append(child)
    found, todo = set(), [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pids: set[int]) -> set[int]:
    return {pid for pid in pids if (fields := proc_stat(pid)) is not None and fields[0] != "Z"}


def test_a_stalled_runners_stage_stops_itself_and_the_runner_records_nothing_when_it_wakes(tiny_shot, tmp_path):
    """SIGSTOP runner A mid-training; B takes the job over once A's lease runs out; SIGCONT A.

    A's training is slowed by a test hook: a tiny training run can finish inside the lease's margin."""
    scan = copy_scans([tiny_shot("2")], tmp_path)[0]
    queue = tmp_path / "queue.sqlite"
    assert batch("add", scan, "--queue", queue).returncode == 0
    run = [*BATCH, "run", "--preset", "tiny", "--lease", "3", "--poll", "0.2", "--backoff", "0", "--queue", str(queue)]
    slow = {**os.environ, "STATION_TEST_SLOW_STEP": f"{STEP_SLEEP}:{scan}",
            "PYTHONPATH": os.pathsep.join([str(FAULT_HOOKS), os.environ.get("PYTHONPATH", "")])}
    with open(tmp_path / "a.log", "wb") as sink:
        runner_a = subprocess.Popen(run, stdout=sink, stderr=sink, env=slow)
    store = JobStore(queue)
    job = store.get(scan)
    helpers: set[int] = set()  # the forkserver and resource tracker: A's processes from before the stage
    while runner_a.poll() is None:
        before = _descendants(runner_a.pid)  # taken before the store is read, so it cannot hold the stage
        if any(e["stage"] == "train" for e in store.stage_events(job.id)):
            break
        helpers = before
        time.sleep(0.02)
    deadline = time.monotonic() + 60
    while not (stage := _alive(_descendants(runner_a.pid) - helpers)) and time.monotonic() < deadline:
        time.sleep(0.01)  # the stage process is forked just after its `started` line
    os.kill(runner_a.pid, signal.SIGSTOP)
    try:
        deadline = time.monotonic() + 60
        while _alive(stage) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert stage and not _alive(stage), "runner A's training went on while A was stopped"
        assert not (scan / "model" / "surface.pt").exists()  # it stopped itself, it did not finish
        with open(tmp_path / "b.log", "wb") as sink:
            runner_b = subprocess.run(run, stdout=sink, stderr=sink, timeout=400)
        assert runner_b.returncode in (0, 1) and store.get(scan).state == "done", (tmp_path / "b.log").read_text()[-3000:]
    except BaseException:
        runner_a.kill()
        raise
    finally:
        os.kill(runner_a.pid, signal.SIGCONT)
    assert runner_a.wait(timeout=120) in (0, 1), (tmp_path / "a.log").read_text()[-3000:]  # 1: quarantined

    log = events(queue, scan)
    trains = [(e["event"], f":{runner_a.pid}:" in e["detail"]["worker"]) for e in log if e["stage"] == "train"]
    # A's training stopped with A's lease, and A, awake again, recorded no outcome of it and no DONE marker
    assert trains == [("started", True), ("started", False), ("finished", False), ("abandoned", True)]
    assert redone_stages(log) == [] and verify_scan(scan) == []
