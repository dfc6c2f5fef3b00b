"""Chaos and Ray: the same batch of four scans survives six SIGKILLs, and runs on Ray to the same verdicts.

The runner is a real `station batch run` subprocess driving the real pipeline on tiny scans. It
is killed at six moments drawn at random and spread over the batch (while a file is being
written, while a model trains, and anywhere), either alone (its stage processes must notice and
stop by themselves) or with its whole process group (a power cut), and restarted each time.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import time
from pathlib import Path

import pytest

from batch_support import (BATCH, TINY_RUN, batch, copy_scans, events, one_ray_at_a_time, proc_stat, process_ids,
                           redone_stages, status, temp_files, verify_scan)
from station.batch.store import JobStore

pytestmark = pytest.mark.slow

STONES = ("1", "2", "3", "4")
# (moment, what is killed): the runner alone (its stage processes must stop by themselves), or its whole
# process group (a power cut; a mid-write kill must be one, so the half-written file stays to be found)
KILLS = (("mid-write", "group"), ("mid-training", "alone"), ("anytime", "group"),
         ("mid-write", "group"), ("mid-training", "group"), ("anytime", "alone"))
SEED = 20261123


@pytest.fixture(scope="module")
def shot(tiny_shot) -> list[Path]:
    return [tiny_shot(stone) for stone in STONES]


def _start_runner(queue: Path, log: Path) -> subprocess.Popen:
    with open(log, "ab") as sink:
        return subprocess.Popen([*BATCH, "run", "--workers", "2", *TINY_RUN, "--queue", str(queue)],
                                stdout=sink, stderr=sink, start_new_session=True)


def _finished_stages(store: JobStore) -> int:
    return sum(e["event"] == "finished" for job in store.jobs() for e in store.stage_events(job.id))


def _in_flight(store: JobStore, pid: int) -> set[tuple[str, str]]:
    """(scan, stage) pairs the runner `pid` has started and not yet ended, from the stage log."""
    open_stages: set[tuple[str, str]] = set()
    for job in store.jobs():
        for event in store.stage_events(job.id):
            key = (Path(job.scan).name, event["stage"])
            if event["event"] == "started" and f":{pid}:" in json.loads(event["detail"]).get("worker", ""):
                open_stages.add(key)
            elif event["event"] in ("finished", "failed", "abandoned"):
                open_stages.discard(key)
    return open_stages


def _wait_for(moment: str, after: int, queue: Path, scans: list[Path], runner: subprocess.Popen,
              rng: random.Random) -> bool:
    """Block until `after` stages have finished in the batch, this runner has a stage under way, and then
    `moment` comes; False if the runner ended first."""
    store = JobStore(queue)
    while runner.poll() is None and (_finished_stages(store) < after or not _in_flight(store, runner.pid)):
        time.sleep(0.05)
    deadline = time.monotonic() + 60
    delay = rng.uniform(0.5, 4.0)
    started = time.monotonic()
    left_over = {path for scan in scans for path in temp_files(scan)}  # from the last kill, not a write now
    while runner.poll() is None and time.monotonic() < deadline:
        if moment == "anytime" and time.monotonic() - started > delay:
            return True
        if moment == "mid-write" and any(set(temp_files(scan)) - left_over for scan in scans):
            return True
        if moment == "mid-training" and any(stage == "train" for _, stage in _in_flight(store, runner.pid)):
            time.sleep(rng.uniform(0.5, 3.0))
            return runner.poll() is None
        time.sleep(0.001 if moment == "mid-write" else 0.1)
    return runner.poll() is None


def _group_gone(pgid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


@pytest.fixture(scope="module")
def chaos_run(shot, tmp_path_factory) -> dict:
    """Four scans, six kills, one final uninterrupted run; what the test needs to judge it."""
    root = tmp_path_factory.mktemp("chaos")
    scans = copy_scans(shot, root / "scans")
    queue = root / "queue.sqlite"
    assert batch("add", *scans, "--queue", queue).returncode == 0
    rng = random.Random(SEED)
    # Spread over the batch: kill k waits for a random number of finished stages first. Of the 12
    # stages, at most 7 may be done, so the last scan still has training and export ahead.
    milestones = sorted(rng.sample(range(8), len(KILLS)))
    kills = []
    for number, ((moment, target), after) in enumerate(zip(KILLS, milestones)):
        runner = _start_runner(queue, root / "runner.log")
        if not _wait_for(moment, after, queue, scans, runner, rng):
            pytest.fail(f"the batch finished before kill {number + 1} ({moment}); see {root / 'runner.log'}")
        alone = target == "alone"
        if alone:
            os.kill(runner.pid, signal.SIGKILL)
        else:
            os.killpg(runner.pid, signal.SIGKILL)  # a power cut: the stage processes die with it
        runner.wait()
        kills.append({"moment": moment, "after": after, "alone": alone, "pid": runner.pid,
                      "finished_stages": _finished_stages(JobStore(queue)),
                      "in_flight": _in_flight(JobStore(queue), runner.pid),
                      # the group holds the runner's forkserver too, which sees its runner gone only once its
                      # preload (torch, numba) is imported: that import alone can outlast 15 s
                      "orphans_stopped": _group_gone(runner.pid, 60.0)})
    final = _start_runner(queue, root / "runner.log")
    final.wait(timeout=500)
    return {"scans": scans, "queue": queue, "kills": kills, "exit": final.returncode, "log": root / "runner.log"}


@pytest.fixture(scope="module")
def ray_run(tiny_shot, tmp_path_factory) -> dict:
    """The four scans on a local Ray instance, set up by this module's first test and holding the machine's one
    Ray slot from before the scans are shot: test_batch_ray_cluster.py, the other module that needs the slot,
    reaches it on the other worker a few seconds into the suite and keeps it for minutes. Asked for after the
    chaos run, as it was, this waited for that whole module; now that module waits for this run instead."""
    root = tmp_path_factory.mktemp("ray")
    with one_ray_at_a_time():
        scans = copy_scans([tiny_shot(stone) for stone in STONES], root / "scans")
        queue = root / "queue.sqlite"
        assert batch("add", *scans, "--queue", queue).returncode == 0
        runner = subprocess.Popen([*BATCH, "run", "--executor", "ray", "--workers", "2", *TINY_RUN, "--queue",
                                   str(queue)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        niceness = _stage_niceness_while(runner, timeout=500)
        stdout, stderr = runner.communicate()
    return {"scans": scans, "queue": queue, "result": subprocess.CompletedProcess(runner.args, runner.returncode,
                                                                                 stdout, stderr),
            "stage_niceness": niceness}


def _stage_niceness_while(runner: subprocess.Popen, timeout: float) -> set[int]:
    """The niceness of every Ray worker seen running a stage (`ray::execute_stage`) until `runner` ends."""
    seen: set[int] = set()
    deadline = time.monotonic() + timeout
    while runner.poll() is None:
        if time.monotonic() > deadline:
            runner.kill()
            runner.wait()
            pytest.fail("the Ray batch did not finish in time")
        for pid in process_ids():
            try:
                running_a_stage = Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::execute_stage")
            except OSError:
                continue
            if running_a_stage and (fields := proc_stat(pid)) is not None:
                seen.add(int(fields[16]))  # field 19 of stat: nice
        time.sleep(0.5)
    return seen


def test_on_a_local_ray_instance_every_file_of_the_batch_verifies(ray_run):
    for scan in ray_run["scans"]:
        assert verify_scan(scan) == [], scan.name


def test_ray_runs_the_stages_at_the_runners_own_priority_not_its_default_nice_15(ray_run):
    assert ray_run["stage_niceness"] == {os.nice(0)}


def test_all_four_scans_end_done_after_six_kills(chaos_run):
    assert len(chaos_run["kills"]) == 6
    jobs = status(chaos_run["queue"])
    assert {name: job["state"] for name, job in jobs.items()} == {s.name: "done" for s in chaos_run["scans"]}, \
        chaos_run["log"].read_text()[-3000:]
    assert all(job["verdict"] in ("pass", "quarantined") for job in jobs.values())


def test_the_kills_landed_mid_write_and_mid_training(chaos_run):
    kills = chaos_run["kills"]
    assert all(k["in_flight"] for k in kills), "a kill hit a runner before it had started any stage"
    assert sum(any(stage == "train" for _, stage in k["in_flight"]) for k in kills) >= 2
    swept = [e for scan in chaos_run["scans"] for e in events(chaos_run["queue"], scan) if e["event"] == "swept"]
    assert swept, "no kill left a half-written temp file behind"


def test_stage_processes_stop_by_themselves_when_the_runner_alone_is_killed(chaos_run):
    assert all(k["orphans_stopped"] for k in chaos_run["kills"] if k["alone"])


def test_every_file_verifies_and_reads_back(chaos_run):
    for scan in chaos_run["scans"]:
        assert verify_scan(scan) == [], scan.name


def test_no_finished_stage_was_ever_redone(chaos_run):
    """A stage runs again only under a new key (its inputs or code changed), never after finishing under its own."""
    logs = {scan.name: events(chaos_run["queue"], scan) for scan in chaos_run["scans"]}
    for name, log in logs.items():
        assert redone_stages(log) == [], name
        assert {e["stage"] for e in log if e["event"] == "finished"} == {"process", "train", "export"}, name
    kept = [e for log in logs.values() for e in log if e["event"] == "skipped"]
    assert kept, "no restart found finished work to keep: the kills did not test it"


def test_the_same_batch_on_a_local_ray_instance_with_two_workers_gets_the_same_verdicts(ray_run, chaos_run):
    on_ray = status(ray_run["queue"])
    local = status(chaos_run["queue"])
    assert {n: (j["state"], j["verdict"]) for n, j in on_ray.items()} == \
        {n: (j["state"], j["verdict"]) for n, j in local.items()}, ray_run["result"].stderr[-3000:]
