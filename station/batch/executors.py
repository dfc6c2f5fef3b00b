"""The local executor: every stage runs in a fresh process that the runner can time out or kill.

A stage process (not a thread) is what makes the budgets real: an over-time stage is killed, a
stage the kernel kills for memory is seen as `died` with its signal, and the memory a stage
grew is returned when it ends. Processes fork from a forkserver that has already imported the
stage modules, so starting one costs milliseconds, not the seconds of importing torch.

A stage process must never outlive the runner that holds its lease (another runner would take
the job over while it still writes): it watches a pipe whose other end only the runner holds,
and exits at once when the runner dies, however it dies.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from typing import Protocol

from station.batch.stage_run import Outcome, StageCall, execute_stage

PRELOAD = ["station.batch.stage_run", "station.process.stage", "station.ngs.pipeline", "station.export.stage"]
ORPHANED_EXIT = 75  # exit status of a stage process whose runner died
POLL_SECONDS = 0.2


class StageExecutor(Protocol):
    """Runs one stage call to an Outcome; `cancel` set means stop it now (lease lost, shutdown)."""

    def run(self, call: StageCall, cancel: threading.Event) -> Outcome: ...

    def close(self) -> None: ...


def _exit_when_orphaned(alive: Connection) -> None:
    try:
        alive.recv()  # nothing is ever sent: this returns only at EOF, when the runner's end closes
    except (EOFError, OSError):
        pass
    os._exit(ORPHANED_EXIT)


def _stage_main(call: StageCall, result: Connection, alive: Connection) -> None:
    threading.Thread(target=_exit_when_orphaned, args=(alive,), daemon=True).start()
    result.send(execute_stage(call))


def _exit_text(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        name = signal.Signals(-exitcode).name
        hint = " (the kernel's out-of-memory killer sends SIGKILL)" if -exitcode == signal.SIGKILL else ""
        return f"killed by {name}{hint}"
    return f"exit status {exitcode}"


class LocalExecutor:
    """Stage processes on this machine; one per running stage."""

    def __init__(self) -> None:
        self.context = multiprocessing.get_context("forkserver")
        self.context.set_forkserver_preload(PRELOAD)

    def run(self, call: StageCall, cancel: threading.Event) -> Outcome:
        result_r, result_w = self.context.Pipe(duplex=False)
        alive_r, alive_w = self.context.Pipe(duplex=False)
        process = self.context.Process(target=_stage_main, args=(call, result_w, alive_r),
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
                        return Outcome("died", f"{call.stage} process {_exit_text(process.exitcode)}")
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
