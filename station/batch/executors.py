"""The local executor: every stage runs in a fresh process that the runner can time out or kill.

A stage process (not a thread) is what makes the budgets real: an over-time stage is killed, a
stage the kernel kills for memory is seen as `died` with its signal, and the memory a stage
grew is returned when it ends. Processes fork from a forkserver that has already imported the
stage modules, so starting one costs milliseconds, not the seconds of importing torch.

A stage process must never outlive the runner that holds its lease (another runner would take
the job over while it still writes): it watches a pipe whose other end only the runner holds,
and exits at once when the runner dies, however it dies. Nor may it outlive the runner's lease
while the runner is alive but stalled (SIGSTOP, a frozen VM): it reads the lease from the store
and stops itself before the lease can run out, so no other runner's stage ever writes beside it.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import socket
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Protocol

from station.batch.stage_run import Outcome, StageCall, execute_stage
from station.batch.store import JobStore, StoreConfig

# torch._dynamo too: torch.optim imports it when a training stage builds its first optimizer, 2-3 s
# that every training stage paid again
PRELOAD = ["station.batch.stage_run", "station.process.stage", "station.ngs.pipeline", "station.export.stage",
           "torch._dynamo"]
ORPHANED_EXIT = 75  # exit status of a stage process whose runner died
FENCED_EXIT = 76  # exit status of a stage process that stopped itself: its runner's lease was lost or ran low
POLL_SECONDS = 0.2
LEASE_MARGIN = 1 / 6  # a stage process stops itself when less than this share of the lease is left
# (the runner renews it every third of the lease: this is two and a half missed beats)


@dataclass(frozen=True)
class Attempt:
    """Whose claim a stage runs under (so the stage can fence itself) and where it must not go again."""

    store: str  # the job store's path
    job: int
    worker: str
    fence: int  # the claim's fencing token
    lease_seconds: float
    avoid: frozenset[str] = frozenset()  # nodes this stage was lost on: place it elsewhere when possible


Placed = Callable[[str], None]  # told the node a stage was placed on, before it runs


class StageExecutor(Protocol):
    """Runs one stage call to an Outcome; `cancel` set means stop it now (lease lost, shutdown).

    `placed` is called once with the node the stage was sent to (before it runs); an Outcome of
    kind `lost` means the node or the worker under the stage failed, not the stage."""

    def run(self, call: StageCall, cancel: threading.Event, attempt: Attempt, placed: Placed) -> Outcome: ...

    def close(self) -> None: ...


def _exit_when_orphaned(alive: Connection) -> None:
    try:
        alive.recv()  # nothing is ever sent: this returns only at EOF, when the runner's end closes
    except (EOFError, OSError):
        pass
    os._exit(ORPHANED_EXIT)


def lease_running_out(attempt: Attempt, store: JobStore) -> bool:
    """True once the claim the stage runs under is gone or has less than its margin left."""
    try:
        left = store.lease_left(attempt.job, attempt.worker, attempt.fence)
    except sqlite3.OperationalError:  # store busy: look again at the next tick
        return False
    return left is None or left < attempt.lease_seconds * LEASE_MARGIN


def attempt_store(attempt: Attempt) -> JobStore:
    return JobStore(attempt.store, StoreConfig(lease_seconds=attempt.lease_seconds))


def _exit_when_fenced(attempt: Attempt) -> None:
    """Stop the stage before its runner's lease can run out: a stalled runner's stage must not write on."""
    store = attempt_store(attempt)
    while not lease_running_out(attempt, store):
        time.sleep(attempt.lease_seconds * LEASE_MARGIN / 2)
    os._exit(FENCED_EXIT)


def _stage_main(call: StageCall, attempt: Attempt, result: Connection, alive: Connection) -> None:
    threading.Thread(target=_exit_when_orphaned, args=(alive,), daemon=True).start()
    threading.Thread(target=_exit_when_fenced, args=(attempt,), daemon=True).start()
    result.send(execute_stage(call))


def _exit_text(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        name = signal.Signals(-exitcode).name
        hint = " (the kernel's out-of-memory killer sends SIGKILL)" if -exitcode == signal.SIGKILL else ""
        return f"killed by {name}{hint}"
    return f"exit status {exitcode}"


def _ended_without_outcome(call: StageCall, exitcode: int | None) -> Outcome:
    if exitcode == FENCED_EXIT:
        return Outcome("cancelled", f"{call.stage} stopped itself: its runner's lease was lost or running out")
    return Outcome("died", f"{call.stage} process {_exit_text(exitcode)}")


class LocalExecutor:
    """Stage processes on this machine; one per running stage."""

    def __init__(self) -> None:
        self.context = multiprocessing.get_context("forkserver")
        self.context.set_forkserver_preload(PRELOAD)

    def run(self, call: StageCall, cancel: threading.Event, attempt: Attempt, placed: Placed) -> Outcome:
        placed(socket.gethostname())
        result_r, result_w = self.context.Pipe(duplex=False)
        alive_r, alive_w = self.context.Pipe(duplex=False)
        process = self.context.Process(target=_stage_main, args=(call, attempt, result_w, alive_r),
                                       name=f"station-{call.stage}")
        process.start()
        result_w.close()
        alive_r.close()
        deadline = time.monotonic() + call.seconds
        try:
            while True:
                if result_r.poll(POLL_SECONDS):
                    try:
                        outcome = result_r.recv()
                    except EOFError:  # the process ended without an outcome
                        process.join()
                        return _ended_without_outcome(call, process.exitcode)
                    process.join()
                    return outcome
                if cancel.is_set():
                    self._kill(process)
                    return Outcome("cancelled", f"{call.stage} stopped by the runner")
                if time.monotonic() > deadline:
                    self._kill(process)
                    return Outcome("timeout", f"{call.stage} ran over its time budget of {call.seconds:g} s")
        finally:
            alive_w.close()
            result_r.close()

    @staticmethod
    def _kill(process: multiprocessing.Process) -> None:
        process.kill()
        process.join()

    def close(self) -> None:
        """Nothing to release: every stage process is joined before `run` returns."""
