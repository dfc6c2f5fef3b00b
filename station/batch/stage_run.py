"""One stage on one scan, as an executor runs it: the call, its outcome, and what a failure means.

`execute_stage` runs inside the executor's process (a local stage process or a Ray worker), so
it never raises for a failing stage: it returns an `Outcome` whose `kind` tells the runner what
to do (park bad input at once, retry a diverged training run with a safer preset, back off on
anything unexpected). Both the call and the outcome are plain data so they cross process
boundaries.
"""

from __future__ import annotations

import errno
import os
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from station.errors import DiskFullError, StationError, TrainingError
from station.pipeline import StageName, output_digest, perform, spec
from station.scanfolder import ScanFolder

OutcomeKind = Literal[
    "ok",
    "bad_input",  # the scan or a parameter is wrong: retrying cannot help
    "diverged",  # TrainingError: NaN/inf in training
    "out_of_memory",
    "disk_full",
    "timeout",  # over the stage's time budget
    "died",  # the stage process vanished (killed by the OS, a crash in native code)
    "cancelled",  # the runner stopped it (lease lost, shutdown)
    "lost",  # the node or worker under it failed (Ray): run it again as it was, elsewhere
    "error",  # anything else: may be transient
]


@dataclass(frozen=True)
class StageCall:
    scan: str  # absolute scan folder path
    stage: StageName
    params: dict[str, Any]  # train: {"method", "preset"}; process: {"training_width"} when set; export: {}
    seconds: float  # time budget
    threads: int  # CPU threads the stage may use


@dataclass
class Outcome:
    kind: OutcomeKind
    message: str = ""
    summary: dict[str, Any] = field(default_factory=dict)  # the stage's small JSON report
    outputs: dict[str, str] = field(default_factory=dict)  # output digest, filled when kind == "ok"
    seconds: float = 0.0  # inside the stage function (the rest of a stage's wall time is the scheduler's)

    @property
    def ok(self) -> bool:
        return self.kind == "ok"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def classify(exc: BaseException) -> OutcomeKind:
    """What a stage's exception means for the batch (see OutcomeKind)."""
    if isinstance(exc, DiskFullError) or (isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)):
        return "disk_full"
    if isinstance(exc, TrainingError):
        return "diverged"
    if isinstance(exc, MemoryError) or type(exc).__name__ == "OutOfMemoryError":  # torch.OutOfMemoryError
        return "out_of_memory"
    if isinstance(exc, RuntimeError) and ("out of memory" in str(exc) or "can't allocate memory" in str(exc)):
        return "out_of_memory"
    if isinstance(exc, StationError) and exc.exit_code == 2:
        return "bad_input"
    return "error"


def limit_threads(threads: int) -> None:
    """Keep N stage processes on N*threads cores: oversubscribed torch/numba threads crawl.

    numba keeps its OpenMP threading layer: the workqueue layer, once chosen here to dodge OpenMP's reset
    of torch's count (`set_num_threads` orders the two instead), made a training step slower
    (bench/results/thread_pools.json). OMP_NUM_THREADS carries the share to the process stage's own
    worker processes (station/process/workers.py), which it also caps."""
    import cv2

    from station.ngs.raster import set_num_threads

    set_num_threads(threads)
    cv2.setNumThreads(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)


def execute_stage(call: StageCall) -> Outcome:
    """Run the stage and hash its outputs; every failure becomes an Outcome, never an exception."""
    started = time.perf_counter()
    seconds = 0.0
    try:
        limit_threads(call.threads)
        _, summary = perform(call.scan, call.stage, call.params)
        seconds = time.perf_counter() - started
        outputs = output_digest(ScanFolder(call.scan), spec(call.stage))
    except Exception as exc:  # noqa: BLE001 - the runner decides per kind; the message keeps the type
        kind = classify(exc)
        where = traceback.extract_tb(exc.__traceback__)[-1]
        message = f"{type(exc).__name__}: {exc}"
        if kind == "error":  # a bug or a transient fault: say where, for the morning summary
            message += f" (at {Path(where.filename).name}:{where.lineno})"
        return Outcome(kind, message, seconds=time.perf_counter() - started)
    return Outcome("ok", summary=summary, outputs=outputs, seconds=seconds)
