"""The overnight batch on a real multi-node Ray cluster on this machine, a worker node killed mid-training.

Ray's own multi-node setup (`ray.cluster_utils.Cluster`: a head and two worker nodes, one CPU
each, every node its own raylet) with token auth on, as `ray start --head` ships it. Three tiny
scans run once without a fault, then again (fresh copies) while one worker node is killed with
SIGKILL as it trains a scan: the lost stage must run again as it was, on another node, and every
scan must reach the verdict it reached without the fault, with nothing lost or run twice.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from batch_support import BATCH, batch, copy_scans, events, one_ray_at_a_time, redone_stages, status, verify_scan
from station.batch.ray_executor import Node, choose_nodes, ray_log_path
from station.batch.store import JobStore

pytestmark = pytest.mark.slow

STONES = ("1", "2", "3")
RUN = ["--executor", "ray", "--workers", "3", "--threads", "1", "--preset", "tiny", "--lease", "10", "--poll", "0.2",
       "--backoff", "0", "--json"]
RAY_LINES = ("(raylet)", "[state-dump]", "worker.py", "Ray cluster")  # what leaked to the terminal before


@pytest.fixture(scope="module")
def shot(tiny_shot) -> list[Path]:
    return [tiny_shot(stone) for stone in STONES]


@pytest.fixture(scope="module")
def ray_env():
    """Token auth on, with a fresh token, Ray's files under a short private temp dir, and the workers at the
    test's own priority (Ray's default nice 15 starves them on a busy machine), as an operator may set it."""
    from ray._raylet import AuthenticationTokenLoader, Config

    tmp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")  # Ray's unix sockets live here: the path must be short
    env = {"RAY_TMPDIR": tmp, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
           "RAY_worker_niceness": "0"}
    with pytest.MonkeyPatch.context() as patch:
        for name, value in env.items():
            patch.setenv(name, value)
        Config.initialize("")  # as Ray's own token set-up does: this process reads the mode and token again
        AuthenticationTokenLoader.instance().reset_cache()
        yield env
    shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(ray_env):
    """A head and two 1-CPU worker nodes."""
    from ray.cluster_utils import Cluster

    with one_ray_at_a_time():
        ray_cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        workers = [ray_cluster.add_node(num_cpus=1) for _ in range(2)]
        try:
            yield {"cluster": ray_cluster, "workers": workers, "env": ray_env,
                   "labels": {n.node_id[:12] for n in [ray_cluster.head_node, *workers]}}
        finally:
            ray_cluster.shutdown()


def _node_of(label: str) -> str:
    return label.rsplit("/", 1)[-1]


def _train_started_on(queue: Path, ids: set[str]) -> str | None:
    """The node id (head) of a worker node some scan is training on now, from the store."""
    store = JobStore(queue)
    for job in store.jobs():
        for event in reversed(store.stage_events(job.id)):
            if event["stage"] == "train" and event["event"] != "started":
                break
            node = _node_of(json.loads(event["detail"]).get("node", ""))
            if event["stage"] == "train" and node in ids:
                return node
    return None


def _run(cluster: dict, scans: list[Path], queue: Path, kill: bool) -> dict:
    assert batch("add", *scans, "--queue", queue).returncode == 0
    command = [*BATCH, "run", *RUN, "--ray-address", cluster["cluster"].address, "--queue", str(queue)]
    runner = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, **cluster["env"]})
    killed = None
    if kill:
        workers = {n.node_id[:12]: n for n in cluster["workers"]}
        deadline = time.monotonic() + 300
        while runner.poll() is None and killed is None and time.monotonic() < deadline:
            killed = _train_started_on(queue, set(workers))
            time.sleep(0.1)
        if killed is not None:
            time.sleep(1.0)  # let the stage get under way on its node
            cluster["cluster"].remove_node(workers[killed], allow_graceful=False)  # SIGKILL: raylet and workers
    stdout, stderr = runner.communicate(timeout=500)
    return {"scans": scans, "queue": queue, "exit": runner.returncode, "stdout": stdout, "stderr": stderr,
            "killed": killed, "jobs": status(queue)}


@pytest.fixture(scope="module")
def clean(cluster, shot, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("clean")
    return _run(cluster, copy_scans(shot, root / "scans"), root / "queue.sqlite", kill=False)


@pytest.fixture(scope="module")
def runs(clean, cluster, shot, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("faulty")
    return {"clean": clean, "faulty": _run(cluster, copy_scans(shot, root / "scans"), root / "queue.sqlite", kill=True)}


def _verdicts(run: dict) -> dict[str, tuple]:
    return {name: (job["state"], job["verdict"]) for name, job in run["jobs"].items()}


def test_without_the_token_the_runner_says_how_to_connect(shot, cluster, tmp_path):
    """First in the module, so its setup shoots the scans and starts the cluster and no batch run's setup adds to
    that; the scans first, which need no Ray, while the other worker may still hold the Ray slot.

    Ray's driver tries the cluster 20 times a second apart before it gives up (RAY_NUM_REDIS_GET_RETRIES);
    the cluster refuses a wrong token on every try, so three show the same refusal in a sixth of the time."""
    scans = copy_scans(shot[:1], tmp_path / "scans")
    queue = tmp_path / "queue.sqlite"
    assert batch("add", *scans, "--queue", queue).returncode == 0
    result = batch("run", *RUN, "--ray-address", cluster["cluster"].address, "--queue", queue,
                   env={**cluster["env"], "RAY_AUTH_TOKEN": secrets.token_hex(32), "RAY_NUM_REDIS_GET_RETRIES": "3"})
    assert result.returncode == 3 and "RAY_AUTH_MODE=token" in result.stderr and "Traceback" not in result.stderr
    assert status(queue)[scans[0].name]["state"] == "queued"


def test_without_a_fault_every_scan_finishes_and_the_stages_spread_over_the_nodes(clean, cluster):
    assert all(state == "done" for state, _ in _verdicts(clean).values()), clean["stderr"][-3000:]
    nodes = {_node_of(e["detail"]["node"]) for scan in clean["scans"] for e in events(clean["queue"], scan)
             if e["event"] == "finished"}
    assert nodes == cluster["labels"], "three scans on three nodes, yet not every node got a stage"


def _sos(scan: Path) -> float:
    return next(c["value"] for c in json.loads((scan / "asset" / "gate.json").read_text())["checks"] if c["name"] == "SOS")


def test_a_node_killed_mid_training_changes_no_verdict(runs):
    faulty = runs["faulty"]
    assert faulty["killed"], "no scan was training on a worker node: the fault never happened"
    assert _verdicts(faulty) == _verdicts(runs["clean"]), faulty["stderr"][-3000:]
    # tiny scans are quarantined whatever the preset: the gate's score tells a rerun as it was from a safer one
    for clean, hit in zip(runs["clean"]["scans"], faulty["scans"]):
        assert _sos(hit) == pytest.approx(_sos(clean), abs=0.01), hit.name


def test_the_lost_training_ran_again_as_it_was_on_another_node(runs):
    faulty = runs["faulty"]
    logs = {scan.name: events(faulty["queue"], scan) for scan in faulty["scans"]}
    lost = [(name, e) for name, log in logs.items() for e in log if e["event"] == "failed"]
    assert [(e["stage"], e["detail"]["kind"], _node_of(e["detail"]["node"])) for _, e in lost] == \
        [("train", "lost", faulty["killed"])]
    name = lost[0][0]
    trains = [e for e in logs[name] if e["stage"] == "train" and e["event"] in ("started", "finished")]
    assert [e["detail"]["preset"] for e in trains] == ["tiny"] * len(trains)  # never the safer preset
    assert _node_of(trains[-1]["detail"]["node"]) != faulty["killed"]


def test_nothing_is_lost_or_run_twice_and_every_file_verifies(runs):
    faulty = runs["faulty"]
    for scan in faulty["scans"]:
        log = events(faulty["queue"], scan)
        assert redone_stages(log) == [], scan.name
        assert sorted(e["stage"] for e in log if e["event"] == "finished") == ["export", "process", "train"]
        assert verify_scan(scan) == [], scan.name


def test_the_store_and_the_summary_name_each_stages_node(runs, cluster):
    faulty = runs["faulty"]
    summary = json.loads(faulty["stdout"])  # stdout is the station's JSON and nothing else
    for row in summary["scans"]:
        assert sorted(row["nodes"]) == ["export", "process", "train"], row
        assert {_node_of(entry.split()[0]) for entries in row["nodes"].values() for entry in entries} <= cluster["labels"]
    failures = [f for row in summary["scans"] for f in row["failures"]]
    assert len(failures) == 1 and failures[0].startswith("train (lost: infrastructure") and faulty["killed"] in failures[0]
    printed = batch("summary", "--queue", faulty["queue"])  # the summary as the operator reads it
    assert printed.returncode == 0 and "(lost)" in printed.stderr and f"{faulty['killed']} (lost), then" in printed.stderr


def test_ray_writes_to_its_log_beside_the_queue_not_to_the_terminal(runs):
    faulty = runs["faulty"]
    terminal = faulty["stdout"] + faulty["stderr"]
    assert not [line for line in terminal.splitlines() if any(mark in line for mark in RAY_LINES)]
    ray_log = ray_log_path(faulty["queue"]).read_text()
    assert "(raylet)" in ray_log and "Connected to Ray cluster" in ray_log


def test_training_prefers_a_gpu_node_and_the_other_stages_keep_off_it():
    cpu_a, cpu_b, gpu = Node("a" * 56, "10.0.0.1", 4, 0), Node("b" * 56, "10.0.0.2", 4, 0), Node("c" * 56, "10.0.0.3", 4, 1)
    nodes = [cpu_a, cpu_b, gpu]
    assert choose_nodes(nodes, "train", {}, frozenset())[0] == gpu
    assert choose_nodes(nodes, "process", {}, frozenset())[-1] == gpu
    assert choose_nodes(nodes, "process", {cpu_a.id: 1}, frozenset())[0] == cpu_b  # spread: the least busy first
    assert choose_nodes(nodes, "train", {}, frozenset({gpu.label}))[-1] == gpu  # lost there: last resort only
    assert choose_nodes([Node("d" * 56, "10.0.0.4", 0, 0)], "export", {}, frozenset()) == []  # no CPU: never


@pytest.fixture(scope="module")
def blind(ray_env, shot, tmp_path_factory) -> dict:
    """A worker node in its own mount namespace, with the scans' folder hidden under an empty tmpfs:
    as a node without the shared storage mounted. The head has no CPU, so it is the only candidate.
    The node is started as an operator's `ray start` is by default: its workers at Ray's nice 15."""
    from ray.cluster_utils import Cluster

    tmp_path = tmp_path_factory.mktemp("blind")
    hidden = tmp_path / "scans"
    if subprocess.run(["unshare", "--mount", "true"], capture_output=True).returncode != 0:
        pytest.skip("unshare --mount is not permitted here (needs root or user namespaces)")
    scan = copy_scans(shot[:1], hidden)[0]
    head = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    head_id = head.head_node.node_id
    ray_start = Path(sys.executable).with_name("ray")
    blind_node = (f"mount -t tmpfs none {hidden} && exec {ray_start} start --address={head.address} --num-cpus=1 "
                  "--block --dashboard-agent-listen-port=0 --metrics-export-port=0 --disable-usage-stats")
    node_env = {name: value for name, value in os.environ.items() if name != "RAY_worker_niceness"}
    with open(tmp_path / "node.log", "wb") as sink:
        node = subprocess.Popen(["unshare", "--mount", "--propagation", "private", "sh", "-c", blind_node],
                                stdout=sink, stderr=sink, start_new_session=True, env=node_env)
    try:
        deadline = time.monotonic() + 120
        while sum(n["Alive"] for n in head.global_state.node_table()) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        node_ids = [n["NodeID"] for n in head.global_state.node_table() if n["Alive"]]
        queue = tmp_path / "queue.sqlite"
        assert batch("add", scan, "--queue", queue).returncode == 0
        result = batch("run", *RUN, "--ray-address", head.address, "--queue", queue, env=ray_env)
    finally:
        os.killpg(node.pid, signal.SIGKILL)
        node.wait()
        head.shutdown()
    blind_id = next(i for i in node_ids if i != head_id)
    return {"scan": scan, "queue": queue, "result": result, "node": blind_id[:12]}


def test_a_node_that_cannot_see_the_scan_folder_gets_no_stage_and_is_named(blind):
    scan, result = blind["scan"], blind["result"]
    job = status(blind["queue"])[scan.name]
    assert job["state"] == "parked" and job["stage"] == "process", result.stderr[-3000:]
    assert "no node of the Ray cluster sees this scan folder" in job["reason"] and "cannot see it" in job["reason"]
    assert "parked" in result.stderr and "cannot see it" in result.stderr  # and the runner's log says so at once
    assert not (scan / "images").exists()  # no stage ran anywhere


def test_a_node_whose_workers_run_at_rays_default_nice_15_is_named_once_with_the_fix(blind):
    warnings = [line for line in blind["result"].stderr.splitlines() if "runs its Ray workers at nice" in line]
    assert len(warnings) == 1, blind["result"].stderr[-3000:]
    assert blind["node"] in warnings[0] and "at nice 15, this runner at nice 0" in warnings[0]
    assert "RAY_worker_niceness=0" in warnings[0]


def test_nodes_started_at_the_runners_priority_draw_no_niceness_warning(clean):
    assert "runs its Ray workers at nice" not in clean["stderr"]
