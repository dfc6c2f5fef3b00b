"""The Ray executor (`pip install 'station[ray]'`): each stage of each scan is one Ray task, placed by us.

The runner's worker slots still claim jobs from the SQLite store and record every outcome
there; Ray runs the stage on the node this module picks: stages spread over the nodes (the
one with the fewest of our stages first), training goes to a node with a GPU when there is
one, and the other stages keep off GPU nodes when they can. Before a stage is sent to a node,
a zero-CPU probe task checks that the node sees the scan folder (shared storage, same path,
same scan.json); a node that does not is named and skipped. The same probe reads the niceness
Ray runs the node's workers at, and the runner warns once about a node whose stages would run
below its own priority (Ray's default is nice 15). Ray never retries a task itself
(`max_retries=0`): retries are the runner's decision, and Ray's exception types tell it which
kind (`lost`: the node, its raylet or the worker under the stage failed; anything the stage
itself met comes back as its own Outcome).

Ray's driver lives in a child process whose stdout and stderr go to a log file beside the
queue: Ray prints raylet and worker messages to the driver's own stdout (whatever
`log_to_driver` says), and the operator's terminal gets the station's lines only. The child
exits when the runner dies, and Ray then ends the stages it owned; it also cancels a stage
whose runner stalled (its lease in the store running out), as a local stage process does.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import secrets
import sys
import threading
import time
from dataclasses import dataclass, replace
from multiprocessing.connection import Client, Connection, Listener
from pathlib import Path
from typing import Any

from station.batch.executors import Attempt, Placed, attempt_store, lease_running_out
from station.batch.stage_run import Outcome, StageCall, execute_stage
from station.errors import BadInputError, StationError
from station.scanfolder import ScanFolder, sha256_file

log = logging.getLogger("station.batch")

POLL_SECONDS = 0.5
START_SECONDS = 120.0  # connecting to (or starting) Ray
PROBE_SECONDS = 60.0
SHUTDOWN_SECONDS = 20.0
# Ray starts its workers at nice 15 by default, which starves the stages behind any busy process; 0 (relative)
# keeps a local instance's stages at the runner's own priority, as the local executor's are
LOCAL_WORKER_NICENESS = 0
# Ray's failures of the machinery under a stage: the stage is run again as it was, on another node
LOST = ("NodeDiedError", "WorkerCrashedError", "LocalRayletDiedError", "ObjectLostError", "RayActorError",
        "TaskUnschedulableError", "RaySystemError")
TOKEN_SOURCES = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


class RayStartError(StationError):
    """Ray could not be reached or started (address, token auth, version)."""

    exit_code = 3


@dataclass(frozen=True)
class Node:
    id: str
    address: str
    cpus: float
    gpus: float

    @property
    def label(self) -> str:
        """How the store and the summary name a node: its address and the head of its Ray node id."""
        return f"{self.address}/{self.id[:12]}"


def choose_nodes(nodes: list[Node], stage: str, busy: dict[str, int], avoid: frozenset[str]) -> list[Node]:
    """Candidate nodes for a stage, best first: training on GPUs, others off them, then the least busy.

    Nodes the stage was lost on come last (a crashed worker's node may still be alive)."""
    usable = [n for n in nodes if n.cpus >= 1]

    def rank(node: Node) -> tuple:
        gpu_first = (node.gpus < 1) if stage == "train" else (node.gpus >= 1)
        return node.label in avoid, gpu_first, busy.get(node.id, 0), -node.cpus, node.label

    return sorted(usable, key=rank)


def scan_fingerprint(scan: str) -> str | None:
    """sha256 of the scan's scan.json as this machine sees it."""
    try:
        return sha256_file(ScanFolder(scan).scan_json)
    except OSError:
        return None


def probe_node(scan: str) -> tuple[str | None, int]:
    """Run on a node by the probe task: the scan's fingerprint there, and the niceness of the node's Ray workers."""
    return scan_fingerprint(scan), os.nice(0)


@dataclass
class Placement:
    node: Node | None
    refused: list[str]  # nodes that do not see the scan, and why
    warnings: list[str]  # for the operator, once per node


def enable_token_auth() -> None:
    """Ray 2.60's `ray start --head` turns on token auth; a client needs RAY_AUTH_MODE=token to send the token.

    Set it when the operator has a token (the variable, its path, or ~/.ray/auth_token) and has not chosen."""
    if "RAY_AUTH_MODE" in os.environ:
        return
    if any(os.environ.get(name) for name in TOKEN_SOURCES) or (Path.home() / ".ray" / "auth_token").is_file():
        os.environ["RAY_AUTH_MODE"] = "token"


class _Driver:
    """Runs inside the driver process: places stages, submits them, maps Ray's failures to Outcomes."""

    def __init__(self, ray: Any):
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        self.ray, self.affinity = ray, NodeAffinitySchedulingStrategy
        self.task = ray.remote(max_retries=0)(execute_stage)
        self.probe = ray.remote(max_retries=0, num_cpus=0)(probe_node)
        self.own_niceness = os.nice(0)
        self.lock = threading.Lock()
        self.busy: dict[str, int] = {}
        self.lost_on: set[str] = set()  # labels of nodes some stage was lost on, until a stage ends well there
        self.seen: set[tuple[str, str]] = set()  # (node id, scan) pairs whose probe matched
        self.niceness_checked: set[str] = set()  # node ids

    def nodes(self) -> list[Node]:
        return [Node(n["NodeID"], n["NodeManagerAddress"], n["Resources"].get("CPU", 0), n["Resources"].get("GPU", 0))
                for n in self.ray.nodes() if n["Alive"]]

    def _sees(self, node: Node, scan: str, expected: str | None, warnings: list[str]) -> str | None:
        """None when the node sees the scan folder, else why not; a warning about the node's niceness, once."""
        if (node.id, scan) in self.seen:
            return None
        ref = self.probe.options(scheduling_strategy=self.affinity(node.id, soft=False)).remote(scan)
        try:
            found, niceness = self.ray.get(ref, timeout=PROBE_SECONDS)
        except self.ray.exceptions.RayError as exc:
            return f"did not answer ({type(exc).__name__}: {_last_line(exc)})"
        with self.lock:
            first_look = node.id not in self.niceness_checked
            self.niceness_checked.add(node.id)
        if first_look and niceness > self.own_niceness:
            warnings.append(_starved(node, niceness, self.own_niceness))
        if found is None:
            return "cannot see it"
        if found != expected:
            return "sees a different scan.json at that path"
        self.seen.add((node.id, scan))
        return None

    def place(self, call: StageCall, avoid: frozenset[str]) -> Placement:
        """The node for this stage (reserved), the nodes refused for not seeing the scan, and warnings.

        Every stage puts the nodes any stage was lost on last: Ray reports a killed node alive for
        seconds after its stages fail, and a stage pinned to it then is lost as well."""
        expected, tried, placement = scan_fingerprint(call.scan), set(), Placement(None, [], [])
        while True:
            with self.lock:  # choose and reserve at once: slots placing together spread over the nodes
                order = [n for n in choose_nodes(self.nodes(), call.stage, self.busy, avoid | self.lost_on)
                         if n.id not in tried]
                if not order:
                    return placement
                node = order[0]
                self.busy[node.id] = self.busy.get(node.id, 0) + 1
            tried.add(node.id)
            why = (self._sees(node, call.scan, expected, placement.warnings) if expected
                   else "cannot be checked: the runner cannot read scan.json")
            if why is None:
                placement.node = node
                return placement
            self.release(node)
            placement.refused.append(f"{node.label} {why}")

    def release(self, node: Node) -> None:
        with self.lock:
            self.busy[node.id] -= 1

    def record_outcome(self, node: Node, outcome: Outcome) -> None:
        with self.lock:
            if outcome.kind == "lost":
                self.lost_on.add(node.label)
            elif outcome.ok:
                self.lost_on.discard(node.label)

    def submit(self, call: StageCall, node: Node) -> Any:
        threads = int(max(1, min(call.threads, node.cpus)))
        resources: dict[str, float] = {"num_cpus": threads}
        if call.stage == "train" and node.gpus >= 1:
            resources["num_gpus"] = 1
        return self.task.options(scheduling_strategy=self.affinity(node.id, soft=False), **resources).remote(
            replace(call, threads=threads))

    def result(self, call: StageCall, ref: Any, node: Node) -> Outcome:
        exceptions = self.ray.exceptions
        try:
            return self.ray.get(ref)
        except exceptions.OutOfMemoryError as exc:  # Ray's memory monitor killed the stage: the stage's own failure
            return Outcome("out_of_memory", f"{call.stage}: Ray's memory monitor killed the task ({_first_line(exc)})")
        except tuple(getattr(exceptions, name) for name in LOST) as exc:
            return Outcome("lost", f"{call.stage} on {node.label}: {type(exc).__name__}: {_first_line(exc)}")
        except exceptions.TaskCancelledError:
            return Outcome("cancelled", f"{call.stage} cancelled")
        except exceptions.RayError as exc:
            return Outcome("error", f"{call.stage}: {type(exc).__name__}: {_first_line(exc)}")

    def serve(self, conn: Connection) -> None:
        """One stage, start to end, for one runner slot on the other end of `conn`."""
        with conn:
            call, attempt = conn.recv()
            store = attempt_store(attempt)
            placement = self.place(call, attempt.avoid)
            node = placement.node
            for warning in placement.warnings:
                conn.send(("warning", warning))
            if node is None:
                conn.send(("outcome", Outcome("bad_input", _unseen(call.scan, placement.refused))))
                return
            try:
                conn.send(("placed", node.label, placement.refused))
                ref = self.submit(call, node)
                while True:
                    ready, _ = self.ray.wait([ref], timeout=POLL_SECONDS)
                    if ready:
                        outcome = self.result(call, ref, node)
                        self.record_outcome(node, outcome)
                        conn.send(("outcome", outcome))
                        return
                    if conn.poll():  # "cancel", or the runner's end closed
                        self.ray.cancel(ref, force=True)
                        conn.send(("outcome", Outcome("cancelled", f"{call.stage} stopped by the runner")))
                        return
                    if lease_running_out(attempt, store):  # the runner stalled: its stage must not run on
                        self.ray.cancel(ref, force=True)
                        conn.send(("outcome", Outcome("cancelled", f"{call.stage} stopped: the runner's lease ran out")))
                        return
            except (EOFError, OSError):
                return
            finally:
                self.release(node)


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [""])[0][:300]


def _last_line(exc: BaseException) -> str:
    """A RayTaskError's last line is the remote exception itself."""
    return (str(exc).strip().splitlines() or [""])[-1][:300]


def _unseen(scan: str, refused: list[str]) -> str:
    asked = "; ".join(refused) or "no node with a CPU is alive"
    return (f"{scan}: no node of the Ray cluster sees this scan folder ({asked}); scan folders must be on "
            "storage every node mounts at the same path (see docs/batch-ray.md)")


def _starved(node: Node, niceness: int, own: int) -> str:
    return (f"node {node.label} runs its Ray workers at nice {niceness}, this runner at nice {own}: stages there get "
            "little CPU beside any other busy process. Start Ray on that node with RAY_worker_niceness=0 in its "
            "environment (docs/batch-ray.md)")


def _exit_with_parent(control: Connection, ray: Any) -> None:
    try:
        control.recv()  # nothing is sent: returns at EOF, when the runner's end closes
    except (EOFError, OSError):
        pass
    threading.Timer(SHUTDOWN_SECONDS, os._exit, (0,)).start()  # a hung shutdown must not keep the process
    ray.shutdown()  # ends this driver's tasks, and a local instance started here
    os._exit(0)


def _driver_main(address: str | None, num_cpus: int | None, log_path: str, key: bytes, control: Connection) -> None:
    """The driver process: Ray's output to `log_path`, then serve stage requests until the runner goes."""
    sink = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(sink, 1)
    os.dup2(sink, 2)
    sys.stdout = sys.stderr = open(1, "w", buffering=1, closefd=False)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, force=True)
    enable_token_auth()
    try:
        import ray

        if address:
            ray.init(address=address, log_to_driver=False)
        else:  # "local": a new instance, never a cluster that `ray start` left running on this machine
            ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                     _system_config={"worker_niceness": LOCAL_WORKER_NICENESS})
        driver = _Driver(ray)
        resources = ray.cluster_resources()
    except Exception as exc:  # noqa: BLE001 - sent back whole: the runner turns it into a clear error
        control.send(("error", f"{type(exc).__name__}: {_first_line(exc)}"))
        return
    listener = Listener(family="AF_UNIX", authkey=key)
    control.send(("ready", listener.address, {"nodes": len(driver.nodes()), "gpus": resources.get("GPU", 0)}))
    threading.Thread(target=_exit_with_parent, args=(control, ray), daemon=True).start()
    while True:
        conn = listener.accept()
        threading.Thread(target=driver.serve, args=(conn,), daemon=True).start()


def ray_log_path(queue: Path) -> Path:
    """Where Ray's own output goes: beside the queue file."""
    return queue.with_name(f"{queue.stem}-ray.log")


class RayExecutor:
    """Stage tasks on an existing cluster (`address`) or on a local instance started here."""

    def __init__(self, log_path: Path, address: str | None = None, num_cpus: int | None = None):
        try:
            import ray  # noqa: F401 - only to fail early and clearly
        except ImportError as exc:
            raise BadInputError("--executor ray needs Ray: pip install 'station[ray]'") from exc
        self.log_path = log_path
        self.key = secrets.token_bytes(32)
        context = multiprocessing.get_context("spawn")
        self.control, child_end = context.Pipe()
        self.process = context.Process(target=_driver_main, name="station-ray-driver",
                                       args=(address, num_cpus, str(log_path), self.key, child_end))
        self.process.start()
        child_end.close()
        if not self.control.poll(START_SECONDS):
            self.close()
            raise RayStartError(f"Ray did not start within {START_SECONDS:g} s; see {log_path}")
        try:
            message = self.control.recv()
        except EOFError:
            message = ("error", f"the Ray driver process ended (exit status {self.process.exitcode})")
        if message[0] == "error":
            self.close()
            where = f"the Ray cluster at {address}" if address else "a local Ray instance"
            raise RayStartError(f"could not connect to {where}: {message[1]}. A cluster started with `ray start` "
                                f"uses token auth: set RAY_AUTH_MODE=token and give the token (docs/batch-ray.md); "
                                f"Ray's log: {log_path}")
        _, self.address, self.cluster = message
        log.info("Ray: %d node(s), %g GPU(s); Ray's own log: %s", self.cluster["nodes"], self.cluster["gpus"], log_path)

    def run(self, call: StageCall, cancel: threading.Event, attempt: Attempt, placed: Placed) -> Outcome:
        deadline = time.monotonic() + call.seconds
        try:
            with Client(self.address, authkey=self.key) as conn:
                conn.send((call, attempt))
                while True:
                    if conn.poll(POLL_SECONDS):
                        message = conn.recv()
                        if message[0] == "outcome":
                            return message[1]
                        if message[0] == "warning":
                            log.warning("%s", message[1])
                            continue
                        _, node, refused = message
                        for line in refused:
                            log.warning("%s: node %s; not sending stages there", Path(call.scan).name, line)
                        placed(node)
                        continue
                    stop = ("cancelled", f"{call.stage} stopped by the runner") if cancel.is_set() else (
                        ("timeout", f"{call.stage} ran over its time budget of {call.seconds:g} s")
                        if time.monotonic() > deadline else None)
                    if stop is not None:
                        conn.send("cancel")
                        conn.poll(PROBE_SECONDS)
                        return Outcome(*stop)
        except (EOFError, OSError) as exc:
            return Outcome("lost", f"{call.stage}: the Ray driver process is gone ({type(exc).__name__}); see {self.log_path}")

    def close(self) -> None:
        self.control.close()  # the driver process exits at EOF; Ray disconnects with it
        self.process.join(30)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
