"""The batch runner: worker slots that claim scans from the job store and drive their stages.

Each slot claims one job at a time, keeps its lease alive from a heartbeat thread, and walks
the stage table. Per stage it computes the key (station.batch.stages); a stage whose record
says done under the same key, with every output still verifying, is skipped; anything else is
cleaned, checked against its disk budget, and run by the executor within its time budget.
Order makes it crash-safe: outputs, then the stage's DONE record, then the store's `finished`
line; a kill anywhere leaves either a verifiable finished stage or one that is redone. The DONE
record is written only after the fence check (the claim's token still holds the lease), so a
runner that stalled past its lease and woke after another runner took the job writes nothing.

What a failure leads to (also in the morning summary):
- bad input (a malformed scan, no usable shot), a full disk, a stage over its time budget:
  parked at once with the reason; retrying cannot help until an operator acts.
- training diverged (TrainingError), ran out of memory, or its process was killed (the
  kernel's OOM killer): retried once with the safer preset (`<preset>-safe`), then parked.
- the machinery under the stage failed (Ray: a node died, a worker crashed, a task was lost
  with its node): the stage runs again as it was, same preset and parameters, on another node
  (at most MAX_LOST times, then the job backs off like any error). Nothing about the scan
  changed, so nothing about its result may.
- anything else: retried with capped, doubling backoff (the store's attempts), then parked.
- frames the process stage flagged (a corrupt raw, a frame with no plausible mask): the scan
  goes on without them and the flags are the job's reason, beside the gate's verdict.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import socket
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station.batch.executors import Attempt, StageExecutor
from station.batch.stage_run import Outcome, StageCall, classify
from station.batch.stages import (
    STAGES,
    Digest,
    StageSpec,
    clean_stage,
    finished_record,
    resumable,
    scan_stage_key,
    sweep_temp_files,
    write_done,
    write_started,
)
from station.batch.store import Job, JobStore
from station.errors import DiskFullError
from station.ngs.preset_names import safer_preset
from station.scanfolder import ScanFolder, require_free_space

log = logging.getLogger("station.batch")

PARK_AT_ONCE = {"bad_input", "disk_full", "timeout"}
SAFER_RETRY = {"diverged", "out_of_memory", "died"}  # for the train stage
MAX_LOST = 3  # a stage lost with its node this often in one attempt: back off instead


@dataclass(frozen=True)
class StageBudget:
    seconds: float  # wall-clock limit; the stage process is killed past it
    free_mb: float  # free space the scan's filesystem must have before the stage starts


DEFAULT_BUDGETS = {
    "process": StageBudget(seconds=2 * 3600, free_mb=2_000),
    "train": StageBudget(seconds=12 * 3600, free_mb=2_000),
    "export": StageBudget(seconds=2 * 3600, free_mb=1_000),
}


def with_budgets(seconds: dict[str, float], free_mb: dict[str, float]) -> dict[str, StageBudget]:
    """The default budgets with the operator's per-stage overrides."""
    return {stage: StageBudget(seconds.get(stage, b.seconds), free_mb.get(stage, b.free_mb))
            for stage, b in DEFAULT_BUDGETS.items()}


@dataclass(frozen=True)
class BatchSettings:
    method: str = "ngs"
    preset: str = "fast"
    training_width: int | None = None  # process: images and masks averaged down to this width; None: as developed
    workers: int = 1
    threads: int = 0  # CPU threads per stage; 0: the machine's cores shared among the workers
    poll_seconds: float = 2.0  # idle wait between claims
    max_lost_starts: int = 10  # a stage started this often with no outcome (the runner keeps dying) is parked
    budgets: dict[str, StageBudget] = field(default_factory=lambda: dict(DEFAULT_BUDGETS))

    def stage_threads(self) -> int:
        return self.threads or max(1, (os.cpu_count() or 1) // self.workers)


class Lease:
    """Heartbeats a claimed job from a thread; sets `cancel` when the lease is lost or the runner stops."""

    def __init__(self, store: JobStore, job: Job, worker: str, stop: threading.Event):
        self.store, self.job, self.worker, self.stop = store, job, worker, stop
        self.cancel = threading.Event()
        self.lost = False
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"lease-{job.id}", daemon=True)
        self._interval = store.config.lease_seconds / 3

    def __enter__(self) -> "Lease":
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._done.set()
        self._thread.join()

    def stage(self, name: str) -> None:
        """Show the job's current stage in `status` (and renew the lease while at it)."""
        if not self._renew(name):
            self._lose()

    def holds(self) -> bool:
        """The fence check before a write for the job outside the store: this claim's token still holds
        an unexpired lease. A store too busy to answer counts as not holding it."""
        try:
            held = self.store.holds(self.job.id, self.worker, self.job.fence)
        except sqlite3.OperationalError:
            held = False
        if not held:
            self._lose()
        return held

    def attempt(self, avoid: frozenset[str] = frozenset()) -> Attempt:
        return Attempt(str(self.store.path), self.job.id, self.worker, self.job.fence,
                       self.store.config.lease_seconds, avoid)

    def _renew(self, stage: str | None = None) -> bool:
        try:
            return self.store.heartbeat(self.job.id, self.worker, stage, self.job.fence)
        except sqlite3.OperationalError:  # store busy: a missed beat; the lease's expiry is the arbiter
            return True

    def _lose(self) -> None:
        self.lost = True
        self.cancel.set()

    def _beat(self) -> None:
        next_beat = time.monotonic() + self._interval
        while not self._done.wait(0.25):
            if self.stop.is_set():
                self.cancel.set()
            if time.monotonic() >= next_beat:
                next_beat = time.monotonic() + self._interval
                if not self._renew():
                    self._lose()
                    return


class JobAbandoned(Exception):
    """The lease was lost or the runner is stopping: leave the job, record nothing more."""


def _events(store: JobStore, job: Job) -> list[dict[str, Any]]:
    """This job's stage log since the operator's last retry, details decoded."""
    events = [{**e, "detail": json.loads(e["detail"] or "{}")} for e in store.stage_events(job.id)]
    starts = [i for i, e in enumerate(events) if e["event"] == "retried"]
    return events[starts[-1] + 1:] if starts else events


def _train_params(settings: BatchSettings, events: list[dict[str, Any]]) -> dict[str, Any]:
    """The configured preset, or its safer twin once a training run diverged or ran out of memory."""
    failed = any(e["stage"] == "train" and e["event"] == "failed" and e["detail"].get("kind") in SAFER_RETRY
                 for e in events)
    return {"method": settings.method, "preset": safer_preset(settings.preset) if failed else settings.preset}


def _stage_params(settings: BatchSettings, stage: str, events: list[dict[str, Any]]) -> dict[str, Any]:
    """What a stage is run with beyond its inputs; part of its key, so a change runs it again."""
    if stage == "train":
        return _train_params(settings, events)
    if stage == "process" and settings.training_width is not None:
        return {"training_width": settings.training_width}
    return {}


def _lost_nodes(events: list[dict[str, Any]], stage: str) -> list[str]:
    """The nodes this stage was lost on (node died, worker crashed) since the operator's last retry."""
    return [e["detail"].get("node", "?") for e in events
            if e["stage"] == stage and e["event"] == "failed" and e["detail"].get("kind") == "lost"]


def _lost_starts(events: list[dict[str, Any]], stage: str, key: str) -> int:
    mine = [e["event"] for e in events if e["stage"] == stage and e["key"] == key]
    return mine.count("started") - sum(mine.count(end) for end in ("finished", "failed", "abandoned"))


def _frame_warnings(summary: dict[str, Any]) -> str | None:
    frames = summary.get("frames") or []
    if not frames:
        return None
    listed = "; ".join(f"{f['file']} ({', '.join(f['flags'])})" for f in frames[:3])
    more = f" and {len(frames) - 3} more" if len(frames) > 3 else ""
    return f"process flagged {len(frames)} frame{'s' if len(frames) > 1 else ''}: {listed}{more}"


class JobRun:
    """One claimed job walked through the stage table by one worker slot."""

    def __init__(self, store: JobStore, job: Job, worker: str, executor: StageExecutor,
                 settings: BatchSettings, lease: Lease):
        self.store, self.job, self.worker = store, job, worker
        self.executor, self.settings, self.lease = executor, settings, lease
        self.scan = ScanFolder(job.scan)
        self.flagged: str | None = None  # the frames process flagged: part of every later verdict or reason

    def run(self) -> None:
        if not self.scan.root.is_dir():
            self.park(f"{self.scan.root}: scan folder not found")
            return
        swept = sweep_temp_files(self.scan)
        if swept:  # a writer was killed mid-write; its target still holds the old content or nothing
            self.store.log_stage(self.job.id, "job", "", "swept", {"files": swept})
        if not self.scan.is_done("capture"):
            self.park(f"{self.scan.root}: no finished capture (stages/capture.json); resume it with `station scan`")
            return
        outputs: dict[str, Digest] = {}
        summaries: dict[str, dict[str, Any]] = {}
        for spec in STAGES:
            done = self._stage(spec, outputs)
            if done is None:
                return
            outputs[spec.name], summaries[spec.name] = done
            if spec.name == "process":
                self.flagged = _frame_warnings(summaries["process"])
        export = summaries["export"]
        gate = None if export.get("pass") else (
            "gate failed: " + "; ".join(export.get("failed_checks", [])) + " (see asset/QUARANTINED.txt)")
        reasons = [r for r in (gate, self.flagged) if r]
        self.store.finish(self.job.id, self.worker, "pass" if export.get("pass") else "quarantined",
                          "; ".join(reasons) or None)

    def _stage(self, spec: StageSpec, outputs: dict[str, Digest]) -> tuple[Digest, dict[str, Any]] | None:
        """Skip, or run (once more with the safer preset if training fails that way); None when the job stopped."""
        while True:
            started = time.perf_counter()
            events = _events(self.store, self.job)
            params = _stage_params(self.settings, spec.name, events)
            key = scan_stage_key(self.scan, spec, params, outputs)
            record = finished_record(self.scan, spec, key)
            if record is not None:
                self.store.log_stage(self.job.id, spec.name, key, "skipped", {"why": "finished earlier; outputs verify"})
                return record["outputs"], record.get("summary", {})
            if _lost_starts(events, spec.name, key) >= self.settings.max_lost_starts:
                self.park(f"{spec.name}: started {self.settings.max_lost_starts} times without an outcome; "
                           "the runner keeps dying in this stage (out of memory?)")
                return None
            outcome = self._execute(spec, key, params, started, frozenset(_lost_nodes(events, spec.name)))
            if outcome.ok:
                return outcome.outputs, outcome.summary
            if outcome.kind == "lost" and len(_lost_nodes(_events(self.store, self.job), spec.name)) < MAX_LOST:
                log.warning("%s: %s lost with its node or worker (%s); running it again as it was, elsewhere",
                            self.scan.root.name, spec.name, outcome.message)
                continue
            preset = params.get("preset")
            if spec.name == "train" and outcome.kind in SAFER_RETRY and safer_preset(preset) != preset:
                log.info("%s: training failed with preset %s (%s); retrying with %s", self.scan.root.name,
                         preset, outcome.kind, safer_preset(preset))
                continue
            self._fail(spec, outcome)
            return None

    def _execute(self, spec: StageSpec, key: str, params: dict[str, Any], started: float,
                 avoid: frozenset[str]) -> Outcome:
        budget = self.settings.budgets[spec.name]
        self.lease.stage(spec.name)
        if self.lease.cancel.is_set() or not self.lease.holds():  # cancelled or taken over: touch nothing
            raise JobAbandoned("lease lost" if self.lease.lost else "runner stopping")
        resumed = resumable(self.scan, spec, key)
        if not resumed:
            clean_stage(self.scan, spec)
        try:
            require_free_space(self.scan.root, int(budget.free_mb * 1e6), f"{spec.name} of {self.scan.root.name}")
        except DiskFullError as exc:
            self.store.log_stage(self.job.id, spec.name, key, "failed", {"kind": "disk_full", "message": str(exc)})
            return Outcome("disk_full", str(exc))
        write_started(self.scan, spec.name, key)
        where: dict[str, str] = {"worker": self.worker}

        def placed(node: str) -> None:
            where["node"] = node
            self.store.log_stage(self.job.id, spec.name, key, "started", {
                "worker": self.worker, "fence": self.job.fence, "node": node, "resumed": resumed, **params})

        call = StageCall(str(self.scan.root), spec.name, params, budget.seconds, self.settings.stage_threads())
        outcome = self.executor.run(call, self.lease.cancel, self.lease.attempt(avoid), placed)
        # the fence check: a runner that stalled past its lease records nothing, least of all a DONE record
        if outcome.kind == "cancelled" or self.lease.cancel.is_set() or not self.lease.holds():
            why = "lease lost" if self.lease.lost else ("runner stopping" if self.lease.stop.is_set() else outcome.message)
            self.store.log_stage(self.job.id, spec.name, key, "abandoned", {"why": why, **where})
            raise JobAbandoned(why)
        if outcome.ok:
            write_done(self.scan, spec.name, key, outcome.outputs, outcome.summary)
            self.store.log_stage(self.job.id, spec.name, key, "finished", {
                "seconds": round(outcome.seconds, 3), "wall": round(time.perf_counter() - started, 3), **where,
                **params})
        else:
            self.store.log_stage(self.job.id, spec.name, key, "failed",
                                 {"kind": outcome.kind, "message": outcome.message, **where, **params})
        return outcome

    def _fail(self, spec: StageSpec, outcome: Outcome) -> None:
        if outcome.kind == "lost":
            nodes = ", ".join(_lost_nodes(_events(self.store, self.job), spec.name))
            job = self.store.fail(self.job.id, self.worker, f"{spec.name}: lost with its node {MAX_LOST} times "
                                  f"({nodes}); the cluster is failing, not the scan", retryable=True)
            log.warning("%s: %s lost %d times, %s", self.scan.root.name, spec.name, MAX_LOST, job.state)
        elif spec.name == "train" and outcome.kind in SAFER_RETRY:
            first, safer = self.settings.preset, safer_preset(self.settings.preset)
            tried = first if first == safer else f"{first} and again with {safer}"
            self.park(f"train failed with preset {tried}: {outcome.message}")
        elif outcome.kind in PARK_AT_ONCE:
            self.park(f"{spec.name}: {outcome.message}")
        else:
            reason = "; ".join(r for r in (self._short(f"{spec.name}: {outcome.message}"), self.flagged) if r)
            job = self.store.fail(self.job.id, self.worker, reason, retryable=True)
            log.warning("%s: %s failed (%s), %s", self.scan.root.name, spec.name, outcome.message, job.state)

    def _short(self, text: str) -> str:
        """Paths inside the scan folder, relative to it: the summary already names the scan."""
        return text.replace(f"{self.scan.root}/", "")

    def park(self, reason: str) -> None:
        reason = "; ".join(r for r in (self._short(reason), self.flagged) if r)  # a flagged frame may be why
        log.warning("%s: parked: %s", self.scan.root.name, reason)
        self.store.fail(self.job.id, self.worker, reason, retryable=False)


def run_job(store: JobStore, job: Job, worker: str, executor: StageExecutor, settings: BatchSettings,
            stop: threading.Event) -> None:
    """Drive one claimed job to done, parked, a backoff, or (lease lost, stopping) nothing at all."""
    with Lease(store, job, worker, stop) as lease:
        run = JobRun(store, job, worker, executor, settings, lease)
        try:
            run.run()
        except JobAbandoned:
            if not lease.lost:
                store.release(job.id, worker)
        except Exception as exc:  # noqa: BLE001 - met outside a stage (hashing inputs, writing a record);
            # one scan's surprise must not end the night's batch
            if classify(exc) in PARK_AT_ONCE:
                run.park(f"{type(exc).__name__}: {exc}")
            else:
                log.exception("%s: runner error", job.scan)
                store.fail(job.id, worker, f"runner error: {type(exc).__name__}: {exc}")


def add_watched(store: JobStore) -> list[Job]:
    """Queue every scan with a finished capture found in the watched folders."""
    added = []
    for folder in store.watches():
        if folder.is_dir():
            for scan in sorted(p for p in folder.iterdir() if (p / "stages" / "capture.json").is_file()):
                added.append(store.add(scan))
    return added


def worker_id(slot: int) -> str:
    """Unique per runner start: a runner restarted under a reused pid must not own its predecessor's leases."""
    return f"{socket.gethostname()}:{os.getpid()}:{slot}:{secrets.token_hex(3)}"


def _worker_loop(store: JobStore, settings: BatchSettings, executor: StageExecutor, slot: int,
                 forever: bool, stop: threading.Event) -> None:
    worker = worker_id(slot)
    while not stop.is_set():
        job = store.claim(worker)
        if job is None:
            if not forever and store.pending() == 0:
                return
            stop.wait(settings.poll_seconds)
            continue
        log.info("%s: claimed %s", worker, Path(job.scan).name)
        run_job(store, job, worker, executor, settings, stop)


def run_batch(store: JobStore, settings: BatchSettings, executor: StageExecutor, forever: bool = False,
              stop: threading.Event | None = None) -> None:
    """Work the queue with `settings.workers` slots until it is empty (or, `forever`, until stopped)."""
    stop = stop or threading.Event()
    add_watched(store)
    slots = [threading.Thread(target=_worker_loop, args=(store, settings, executor, slot, forever, stop),
                              name=f"batch-worker-{slot}") for slot in range(settings.workers)]
    for thread in slots:
        thread.start()
    try:
        while any(thread.is_alive() for thread in slots):
            for thread in slots:
                thread.join(settings.poll_seconds / len(slots))
            if forever:
                add_watched(store)
    except KeyboardInterrupt:
        stop.set()
        for thread in slots:
            thread.join()
        raise
    finally:
        executor.close()
