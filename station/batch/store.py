"""The overnight job store: one SQLite file (WAL) that is the single source of truth.

One job per scan. A worker claims a job with a lease it must renew by heartbeat; a lease that
expires (the worker was killed, the machine lost power) puts the job back in the queue. Each
claim draws the job's next fencing token: a worker checks its token (`holds`) before writing a
stage's done record, so a runner that stalled past its lease (SIGSTOP, a frozen VM) and woke up
after another took the job over writes nothing. Failed
attempts back off and are capped; a job out of attempts is parked (quarantined) with the reason.
Every state change is one short transaction, so a SIGKILL at any moment leaves the store
consistent: SQLite's WAL journal makes each commit atomic and durable.
"""

from __future__ import annotations

import json
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from station.errors import BadInputError

JobState = Literal["queued", "running", "done", "parked", "cancelled"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY,
    scan TEXT NOT NULL UNIQUE,
    state TEXT NOT NULL DEFAULT 'queued',
    stage TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    not_before REAL NOT NULL DEFAULT 0,
    lease_owner TEXT,
    lease_expires REAL,
    fence INTEGER NOT NULL DEFAULT 0,
    verdict TEXT,
    reason TEXT,
    added REAL NOT NULL,
    updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS stage_log (
    id INTEGER PRIMARY KEY,
    job INTEGER NOT NULL REFERENCES jobs(id),
    stage TEXT NOT NULL,
    key TEXT NOT NULL,
    event TEXT NOT NULL,
    detail TEXT,
    at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS stage_log_job ON stage_log(job, stage);
CREATE TABLE IF NOT EXISTS watches (
    folder TEXT PRIMARY KEY,
    added REAL NOT NULL
);
"""


@dataclass(frozen=True)
class StoreConfig:
    lease_seconds: float = 60.0
    max_attempts: int = 3
    backoff_seconds: float = 30.0  # doubled after each failed attempt


@dataclass(frozen=True)
class Job:
    id: int
    scan: str
    state: JobState
    stage: str | None
    attempts: int
    verdict: str | None
    reason: str | None
    lease_owner: str | None
    fence: int = 0  # the fencing token of the current (or last) claim; each claim draws the next

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


class JobStore:
    """Queue operations on the SQLite file at `path`; safe to use from several processes."""

    def __init__(self, path: Path | str, config: StoreConfig | None = None, clock=time.time):
        self.path = Path(path)
        self.config = config or StoreConfig()
        self.clock = clock
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with closing(self._connect()) as db:
            try:  # a malformed page surfaces here, not in the middle of a later query
                db.executescript(_SCHEMA)
                check = db.execute("PRAGMA quick_check").fetchone()[0]
            except sqlite3.DatabaseError as exc:
                raise BadInputError(f"{self.path}: not a usable job store ({exc})") from exc
            if check != "ok":
                raise BadInputError(f"{self.path}: job store is damaged ({check})")
            if "fence" not in {row["name"] for row in db.execute("PRAGMA table_info(jobs)")}:
                db.execute("ALTER TABLE jobs ADD COLUMN fence INTEGER NOT NULL DEFAULT 0")  # a queue from before fencing

    def _connect(self) -> sqlite3.Connection:
        try:
            db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
        except sqlite3.DatabaseError as exc:
            raise BadInputError(f"{self.path}: not a usable job store ({exc})") from exc
        db.row_factory = sqlite3.Row
        return db

    def _transaction(self):
        db = self._connect()
        db.execute("BEGIN IMMEDIATE")
        return _Transaction(db)

    # -- queue -----------------------------------------------------------------------------
    def add(self, scan: Path | str) -> Job:
        """Queue a scan once; adding it again returns the existing job unchanged."""
        key = str(Path(scan).resolve())
        now = self.clock()
        with self._transaction() as db:
            db.execute("INSERT OR IGNORE INTO jobs(scan, added, updated) VALUES (?, ?, ?)", (key, now, now))
        return self.get(key)

    def claim(self, worker: str) -> Job | None:
        """Lease the oldest runnable job to `worker`, first requeueing any whose lease expired."""
        now = self.clock()
        with self._transaction() as db:
            self._requeue_expired(db, now)
            row = db.execute(
                "SELECT id FROM jobs WHERE state='queued' AND not_before <= ? ORDER BY added, id LIMIT 1", (now,)
            ).fetchone()
            if row is None:
                return None
            db.execute(
                "UPDATE jobs SET state='running', lease_owner=?, lease_expires=?, fence=fence+1, updated=? WHERE id=?",
                (worker, now + self.config.lease_seconds, now, row["id"]),
            )
        return self.get_by_id(row["id"])

    def holds(self, job_id: int, worker: str, fence: int) -> bool:
        """The fence check: True, and the lease renewed, only while `worker` holds the claim that drew `fence`
        and its lease has not run out. Called before anything is written for the job outside the store."""
        now = self.clock()
        with self._transaction() as db:
            cursor = db.execute(
                "UPDATE jobs SET lease_expires=?, updated=? "
                "WHERE id=? AND lease_owner=? AND fence=? AND state='running' AND lease_expires >= ?",
                (now + self.config.lease_seconds, now, job_id, worker, fence, now),
            )
            return cursor.rowcount == 1

    def lease_left(self, job_id: int, worker: str, fence: int) -> float | None:
        """Seconds left on the claim that drew `fence` (read only, for a stage process watching its runner's
        lease); None when that claim is gone (taken over, cancelled, finished)."""
        with closing(self._connect()) as db:
            row = db.execute("SELECT lease_owner, fence, state, lease_expires FROM jobs WHERE id=?", (job_id,)).fetchone()
        if row is None or (row["lease_owner"], row["fence"], row["state"]) != (worker, fence, "running"):
            return None
        return row["lease_expires"] - self.clock()

    def heartbeat(self, job_id: int, worker: str, stage: str | None = None, fence: int | None = None) -> bool:
        """Renew the lease (of the claim that drew `fence`, when given); False means the lease was lost
        (expired and taken, or cancelled) and work must stop."""
        now = self.clock()
        with self._transaction() as db:
            cursor = db.execute(
                "UPDATE jobs SET lease_expires=?, stage=COALESCE(?, stage), updated=? "
                "WHERE id=? AND lease_owner=? AND state='running' AND fence=COALESCE(?, fence)",
                (now + self.config.lease_seconds, stage, now, job_id, worker, fence),
            )
            return cursor.rowcount == 1

    def finish(self, job_id: int, worker: str, verdict: str, reason: str | None = None) -> None:
        self._release(job_id, worker, "done", verdict=verdict, reason=reason)

    def fail(self, job_id: int, worker: str, reason: str, retryable: bool = True) -> Job:
        """Record a failed attempt: back off and requeue, or park when attempts run out."""
        now = self.clock()
        with self._transaction() as db:
            row = db.execute("SELECT attempts FROM jobs WHERE id=? AND lease_owner=?", (job_id, worker)).fetchone()
            if row is not None:
                attempts = row["attempts"] + 1
                if retryable and attempts < self.config.max_attempts:
                    delay = self.config.backoff_seconds * 2 ** (attempts - 1)
                    db.execute(
                        "UPDATE jobs SET state='queued', attempts=?, not_before=?, lease_owner=NULL, "
                        "lease_expires=NULL, reason=?, updated=? WHERE id=?",
                        (attempts, now + delay, reason, now, job_id),
                    )
                else:
                    db.execute(
                        "UPDATE jobs SET state='parked', attempts=?, lease_owner=NULL, lease_expires=NULL, "
                        "reason=?, updated=? WHERE id=?",
                        (attempts, reason, now, job_id),
                    )
        return self.get_by_id(job_id)

    def retry(self, scan: Path | str) -> Job:
        """Operator action: give a parked or cancelled scan a fresh set of attempts.

        A `retried` line in the stage log marks where the fresh start begins: failures before it
        (a diverged training run, a lost stage) no longer count against the scan."""
        job = self.get(scan)
        now = self.clock()
        with self._transaction() as db:
            cursor = db.execute(
                "UPDATE jobs SET state='queued', attempts=0, not_before=0, verdict=NULL, reason=NULL, updated=? "
                "WHERE id=? AND state IN ('parked', 'cancelled', 'done')",
                (now, job.id),
            )
            if cursor.rowcount:
                db.execute("INSERT INTO stage_log(job, stage, key, event, detail, at) VALUES (?, 'job', '', 'retried', '{}', ?)",
                           (job.id, now))
        return self.get_by_id(job.id)

    def release(self, job_id: int, worker: str) -> None:
        """Hand a job back untouched (the runner is shutting down): queued again, no attempt spent."""
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET state='queued', lease_owner=NULL, lease_expires=NULL, updated=? "
                "WHERE id=? AND lease_owner=? AND state='running'",
                (self.clock(), job_id, worker),
            )

    def cancel(self, scan: Path | str) -> Job:
        job = self.get(scan)
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET state='cancelled', lease_owner=NULL, lease_expires=NULL, updated=? WHERE id=?",
                (self.clock(), job.id),
            )
        return self.get_by_id(job.id)

    # -- stage log -------------------------------------------------------------------------
    def log_stage(self, job_id: int, stage: str, key: str, event: str, detail: dict | None = None) -> None:
        """Append to the per-stage log (started/finished/skipped/failed) used to prove no work was redone."""
        with self._transaction() as db:
            db.execute(
                "INSERT INTO stage_log(job, stage, key, event, detail, at) VALUES (?, ?, ?, ?, ?, ?)",
                (job_id, stage, key, event, json.dumps(detail or {}), self.clock()),
            )

    def stage_events(self, job_id: int) -> list[dict]:
        with closing(self._connect()) as db:
            rows = db.execute("SELECT stage, key, event, detail, at FROM stage_log WHERE job=? ORDER BY id", (job_id,))
            return [dict(row) for row in rows]

    # -- watched folders -------------------------------------------------------------------
    def add_watch(self, folder: Path | str) -> None:
        """Remember a folder whose finished scans the runner keeps adding (`station batch add --watch`)."""
        with self._transaction() as db:
            db.execute("INSERT OR IGNORE INTO watches(folder, added) VALUES (?, ?)",
                       (str(Path(folder).resolve()), self.clock()))

    def watches(self) -> list[Path]:
        with closing(self._connect()) as db:
            return [Path(row["folder"]) for row in db.execute("SELECT folder FROM watches ORDER BY added")]

    # -- reads -----------------------------------------------------------------------------
    def get(self, scan: Path | str) -> Job:
        key = str(Path(scan).resolve())
        with closing(self._connect()) as db:
            row = db.execute("SELECT * FROM jobs WHERE scan=?", (key,)).fetchone()
        if row is None:
            raise BadInputError(f"{self.path}: no job for scan {key}")
        return _job(row)

    def get_by_id(self, job_id: int) -> Job:
        with closing(self._connect()) as db:
            row = db.execute("SELECT * FROM jobs WHERE id=?", (job_id,)).fetchone()
        if row is None:
            raise BadInputError(f"{self.path}: no job with id {job_id}")
        return _job(row)

    def jobs(self) -> list[Job]:
        with closing(self._connect()) as db:
            return [_job(row) for row in db.execute("SELECT * FROM jobs ORDER BY added, id")]

    def pending(self) -> int:
        """Jobs that still need a worker (queued or running)."""
        with closing(self._connect()) as db:
            return db.execute("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')").fetchone()[0]

    # -- internals -------------------------------------------------------------------------
    def _requeue_expired(self, db: sqlite3.Connection, now: float) -> None:
        db.execute(
            "UPDATE jobs SET state='queued', lease_owner=NULL, lease_expires=NULL, updated=? "
            "WHERE state='running' AND lease_expires < ?",
            (now, now),
        )

    def _release(self, job_id: int, worker: str, state: JobState, verdict: str | None, reason: str | None) -> None:
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET state=?, verdict=?, reason=?, lease_owner=NULL, lease_expires=NULL, updated=? "
                "WHERE id=? AND lease_owner=?",
                (state, verdict, reason, self.clock(), job_id, worker),
            )


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT (or ROLLBACK on error), then close the connection."""

    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self) -> sqlite3.Connection:
        return self.db

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.db.execute("ROLLBACK" if exc_type else "COMMIT")
        finally:
            self.db.close()


def _job(row: sqlite3.Row) -> Job:
    return Job(
        id=row["id"],
        scan=row["scan"],
        state=row["state"],
        stage=row["stage"],
        attempts=row["attempts"],
        verdict=row["verdict"],
        reason=row["reason"],
        lease_owner=row["lease_owner"],
        fence=row["fence"],
    )
