"""The overnight job store: leases, expiry, capped attempts with backoff, parking, operator actions."""

import multiprocessing
import os
import signal
import sqlite3
import time

import pytest

from station.batch.store import JobStore, StoreConfig
from station.errors import BadInputError

pytestmark = pytest.mark.no_kernels


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


@pytest.fixture
def clock():
    return Clock()


@pytest.fixture
def store(tmp_path, clock):
    return JobStore(tmp_path / "queue.sqlite", StoreConfig(lease_seconds=10, max_attempts=3, backoff_seconds=5), clock=clock)


def test_adding_a_scan_twice_keeps_one_job(store, tmp_path):
    first = store.add(tmp_path / "scan_a")
    again = store.add(tmp_path / "scan_a")
    assert first.id == again.id
    assert len(store.jobs()) == 1


def test_a_claimed_job_is_not_given_to_a_second_worker(store, tmp_path):
    store.add(tmp_path / "scan_a")
    assert store.claim("w1").lease_owner == "w1"
    assert store.claim("w2") is None


def test_an_expired_lease_is_requeued_and_the_old_worker_learns_it_lost_it(store, tmp_path, clock):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    clock.now += 11
    assert store.claim("w2").lease_owner == "w2"
    assert not store.heartbeat(job.id, "w1")
    assert store.heartbeat(job.id, "w2", stage="train")
    assert store.get_by_id(job.id).stage == "train"


def test_heartbeats_keep_a_lease_alive(store, tmp_path, clock):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    for _ in range(5):
        clock.now += 8
        assert store.heartbeat(job.id, "w1")
    assert store.claim("w2") is None


def test_failures_back_off_then_park_with_the_reason(store, tmp_path, clock):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    after_first = store.fail(job.id, "w1", "training diverged")
    assert after_first.state == "queued" and after_first.attempts == 1
    assert store.claim("w1") is None  # still backing off
    clock.now += 5
    store.claim("w1")
    store.fail(job.id, "w1", "training diverged")
    clock.now += 10
    store.claim("w1")
    parked = store.fail(job.id, "w1", "training diverged again")
    assert (parked.state, parked.attempts, parked.reason) == ("parked", 3, "training diverged again")
    assert store.pending() == 0


def test_non_retryable_failure_parks_at_once(store, tmp_path):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    assert store.fail(job.id, "w1", "corrupt raw raw/e0_a003.dng", retryable=False).state == "parked"


def test_retry_and_cancel_are_operator_actions(store, tmp_path):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    store.fail(job.id, "w1", "disk full", retryable=False)
    assert store.retry(tmp_path / "scan_a").state == "queued"
    assert store.cancel(tmp_path / "scan_a").state == "cancelled"
    assert store.claim("w1") is None


def test_finishing_records_the_verdict(store, tmp_path):
    job = store.add(tmp_path / "scan_a")
    store.claim("w1")
    store.finish(job.id, "w1", verdict="pass")
    done = store.get_by_id(job.id)
    assert (done.state, done.verdict, done.lease_owner) == ("done", "pass", None)


def test_unknown_scan_is_a_clear_error(store, tmp_path):
    with pytest.raises(BadInputError, match="no job for scan"):
        store.get(tmp_path / "nope")


def test_a_garbage_file_is_refused_as_a_job_store(tmp_path):
    bad = tmp_path / "queue.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(BadInputError, match="queue.sqlite"):
        JobStore(bad)


def _claim_then_die(path):
    store = JobStore(path, StoreConfig(lease_seconds=0.5))
    store.claim("doomed")
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_killed_holding_a_lease_loses_no_job(tmp_path):
    path = tmp_path / "queue.sqlite"
    store = JobStore(path, StoreConfig(lease_seconds=0.5))
    store.add(tmp_path / "scan_a")
    process = multiprocessing.get_context("spawn").Process(target=_claim_then_die, args=(path,))
    process.start()
    process.join(30)
    assert process.exitcode == -signal.SIGKILL
    assert store.jobs()[0].lease_owner == "doomed"
    time.sleep(0.6)
    assert store.claim("survivor").scan == str((tmp_path / "scan_a").resolve())


def test_each_claim_draws_a_new_fencing_token_and_a_stale_one_never_holds(store, tmp_path, clock):
    job = store.add(tmp_path / "scan_a")
    first = store.claim("w1")
    assert store.holds(job.id, "w1", first.fence) and store.lease_left(job.id, "w1", first.fence) == 10
    clock.now += 11  # w1 stalled past its lease: no longer holds it, even before anyone takes it over
    assert not store.holds(job.id, "w1", first.fence)
    second = store.claim("w2")
    assert second.fence == first.fence + 1
    assert not store.holds(job.id, "w1", first.fence) and store.lease_left(job.id, "w1", first.fence) is None
    assert not store.heartbeat(job.id, "w1", fence=first.fence)
    assert store.holds(job.id, "w2", second.fence) and not store.holds(job.id, "w2", first.fence)


def test_a_queue_from_before_fencing_gains_the_column(tmp_path):
    path = tmp_path / "queue.sqlite"
    JobStore(path)
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE jobs DROP COLUMN fence")
    db.execute("INSERT INTO jobs(scan, added, updated) VALUES ('/scans/a', 0, 0)")
    db.commit()
    db.close()
    store = JobStore(path)
    assert store.claim("w1").fence == 1
