"""The Ray executor (`pip install 'station[ray]'`): each stage of each scan is one Ray task.

The runner's worker slots still claim jobs from the SQLite store and record every outcome
there; Ray only places the stage where its resources are (a GPU for training when the cluster
has one, else one CPU slot per thread) and runs it. Scan folders must be on storage every node
sees. Ray never retries a task itself (`max_retries=0`): retries are the store's decision.
A task whose driver dies is cleaned up by Ray (its owner is gone), so no stage outlives the
lease of the runner that started it.
"""

from __future__ import annotations

import threading
import time

from station.batch.stage_run import Outcome, StageCall, execute_stage
from station.errors import BadInputError

POLL_SECONDS = 0.5


class RayExecutor:
    """Stage tasks on an existing cluster (`address`) or on a local instance started here."""

    def __init__(self, address: str | None = None, num_cpus: int | None = None):
        try:
            import ray
        except ImportError as exc:
            raise BadInputError("--executor ray needs Ray: pip install 'station[ray]'") from exc
        self.ray = ray
        self.started_here = not ray.is_initialized()
        if self.started_here:
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
        self.has_gpus = ray.cluster_resources().get("GPU", 0) > 0
        self.task = ray.remote(max_retries=0)(execute_stage)

    def resources(self, call: StageCall) -> dict[str, float]:
        if call.stage == "train" and self.has_gpus:
            return {"num_gpus": 1, "num_cpus": 1}
        return {"num_cpus": call.threads}

    def run(self, call: StageCall, cancel: threading.Event) -> Outcome:
        exceptions = self.ray.exceptions
        ref = self.task.options(**self.resources(call)).remote(call)
        deadline = time.monotonic() + call.seconds
        while True:
            ready, _ = self.ray.wait([ref], timeout=POLL_SECONDS)
            if ready:
                try:
                    return self.ray.get(ref)
                except exceptions.OutOfMemoryError as exc:
                    return Outcome("out_of_memory", f"{call.stage}: Ray's memory monitor killed the task ({exc})")
                except (exceptions.WorkerCrashedError, exceptions.NodeDiedError) as exc:
                    return Outcome("died", f"{call.stage}: the Ray worker died ({type(exc).__name__})")
                except exceptions.TaskCancelledError:
                    return Outcome("cancelled", f"{call.stage} cancelled")
                except exceptions.RayError as exc:
                    return Outcome("error", f"{call.stage}: {type(exc).__name__}: {exc}")
            if cancel.is_set():
                self.ray.cancel(ref, force=True)
                return Outcome("cancelled", f"{call.stage} stopped by the runner")
            if time.monotonic() > deadline:
                self.ray.cancel(ref, force=True)
                return Outcome("timeout", f"{call.stage} ran over its time budget of {call.seconds:g} s")

    def close(self) -> None:
        if self.started_here:
            self.ray.shutdown()
