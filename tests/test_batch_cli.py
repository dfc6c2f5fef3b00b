"""`station batch` from the operator's side: queueing, status, retry/cancel, bad input, the morning summary.

The queue's states are set through the job store directly, so no stage runs here; the batch runs
themselves are tested in test_batch_chaos.py and test_batch_faults.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from station.batch.runner import add_watched
from station.batch.store import JobStore
from station.cli_batch import batch_app
from station.scanfolder import ScanFolder

pytestmark = pytest.mark.no_kernels

runner = CliRunner()


def finished_capture(root: Path) -> Path:
    ScanFolder(root).mark_done("capture", {"frames": 0})
    return root


def invoke(*args: object, env: dict | None = None):
    return runner.invoke(batch_app, [str(a) for a in args], env=env)


@pytest.fixture
def queue(tmp_path) -> Path:
    """A queue with a passed, a parked and a queued scan, and a stage log for the first two."""
    path = tmp_path / "queue.sqlite"
    store = JobStore(path)
    passed, parked, waiting = (finished_capture(tmp_path / name) for name in ("a_pass", "b_parked", "c_waiting"))
    for scan in (passed, parked, waiting):
        store.add(scan)
    job = store.claim("w")
    store.log_stage(job.id, "train", "k", "finished", {"seconds": 12.5})
    store.finish(job.id, "w", "pass")
    job = store.claim("w")
    store.log_stage(job.id, "train", "k", "failed", {"kind": "diverged", "preset": "tiny", "message": "NaN <at> step 5"})
    store.fail(job.id, "w", "train failed with preset tiny and again with tiny-safe: <NaN>", retryable=False)
    return path


def test_status_json_gives_each_scan_state_stage_verdict_and_reason(queue):
    result = invoke("status", "--queue", queue, "--json")
    assert result.exit_code == 0
    jobs = {Path(j["scan"]).name: j for j in json.loads(result.stdout)["jobs"]}
    assert (jobs["a_pass"]["state"], jobs["a_pass"]["verdict"]) == ("done", "pass")
    assert jobs["b_parked"]["state"] == "parked" and jobs["b_parked"]["reason"].startswith("train failed")
    assert jobs["c_waiting"]["state"] == "queued" and set(jobs["c_waiting"]) >= {"stage", "verdict", "reason"}


def test_the_queue_file_comes_from_station_queue_when_not_given(queue):
    result = invoke("status", "--json", env={"STATION_QUEUE": str(queue)})
    assert result.exit_code == 0 and len(json.loads(result.stdout)["jobs"]) == 3


def test_adding_a_folder_without_a_finished_capture_is_refused(tmp_path):
    (tmp_path / "half").mkdir()
    result = invoke("add", tmp_path / "half", "--queue", tmp_path / "q.sqlite")
    assert result.exit_code == 2
    assert "half" in result.output and "capture" in result.output


def test_a_watched_folder_queues_its_finished_scans_now_and_later(tmp_path):
    inbox = tmp_path / "inbox"
    finished_capture(inbox / "done_scan")
    (inbox / "still_shooting" / "raw").mkdir(parents=True)
    path = tmp_path / "q.sqlite"
    result = invoke("add", "--watch", inbox, "--queue", path, "--json")
    assert result.exit_code == 0
    assert [Path(j["scan"]).name for j in json.loads(result.stdout)["jobs"]] == ["done_scan"]
    finished_capture(inbox / "still_shooting")  # the capture ends while the runner runs
    store = JobStore(path)
    add_watched(store)
    assert [Path(j.scan).name for j in store.jobs()] == ["done_scan", "still_shooting"]


def test_retry_requeues_a_parked_scan_and_cancel_takes_one_out(queue, tmp_path):
    retried = invoke("retry", tmp_path / "b_parked", "--queue", queue, "--json")
    assert retried.exit_code == 0
    assert (json.loads(retried.stdout)["state"], json.loads(retried.stdout)["reason"]) == ("queued", None)
    cancelled = invoke("cancel", tmp_path / "c_waiting", "--queue", queue, "--json")
    assert json.loads(cancelled.stdout)["state"] == "cancelled"


def test_commands_on_a_missing_queue_or_an_unknown_scan_are_usage_errors(queue, tmp_path):
    for command in (["status"], ["retry", tmp_path / "a_pass"], ["cancel", tmp_path / "a_pass"], ["summary"]):
        result = invoke(*command, "--queue", tmp_path / "nope.sqlite")
        assert result.exit_code == 2 and "nope.sqlite" in result.output
    assert invoke("retry", tmp_path / "never_added", "--queue", queue).exit_code == 2


@pytest.mark.parametrize("bad", [["--time-budget", "polish=10"], ["--disk-budget", "train=lots"],
                                 ["--preset", "huge"], ["--method", "nerf"], ["--executor", "slurm"]])
def test_bad_run_options_are_refused_before_any_work(queue, bad):
    result = invoke("run", *bad, "--queue", queue)
    assert result.exit_code == 2
    assert JobStore(queue).pending() == 1  # c_waiting is still waiting


def test_the_morning_summary_html_is_self_contained_and_names_every_scan(queue, tmp_path):
    page_path = tmp_path / "morning.html"
    result = invoke("summary", "--html", page_path, "--queue", queue, "--json")
    assert result.exit_code == 0
    summary = json.loads(result.stdout)
    assert summary["counts"] == {"pass": 1, "parked": 1, "queued": 1}
    page = page_path.read_text()
    for name in ("a_pass", "b_parked", "c_waiting", "PASS", "12.5 s", "diverged: the training itself diverged, preset tiny"):
        assert name in page
    assert "&lt;NaN&gt;" in page and "<NaN>" not in page  # reasons are escaped, never markup
    assert "<script" not in page and "src=" not in page and "http" not in page


def test_running_an_empty_queue_writes_the_summary_and_exits_0(tmp_path):
    path = tmp_path / "q.sqlite"
    result = invoke("run", "--queue", path, "--json")
    assert result.exit_code == 0
    assert Path(json.loads(result.stdout)["summary_html"]) == tmp_path / "q-summary.html"
    assert (tmp_path / "q-summary.html").is_file()


def test_a_runner_starts_without_importing_torch_which_only_its_stage_processes_need(tmp_path):
    """A runner restarted after a crash paid some 5 s of imports it never used before it could claim a scan."""
    started = subprocess.run([sys.executable, "-X", "importtime", "-m", "station.cli_batch", "run",
                              "--preset", "tiny", "--queue", str(tmp_path / "q.sqlite")],
                             capture_output=True, text=True, timeout=120)
    assert started.returncode == 0, started.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in started.stderr.splitlines() if line.startswith("import time:")}
    assert "station.batch.runner" in imported
    assert not imported & {"torch", "numba", "cv2", "scipy"}


def test_the_summary_tells_a_lost_node_from_a_failed_training_and_says_where_each_attempt_ran(tmp_path):
    path = tmp_path / "queue.sqlite"
    store = JobStore(path)
    store.add(finished_capture(tmp_path / "stone"))
    job = store.claim("w")
    for stage, event, detail in (
            ("process", "finished", {"seconds": 3.0, "node": "10.0.0.1/aaaa"}),
            ("train", "failed", {"kind": "lost", "preset": "fast", "node": "10.0.0.2/bbbb", "message": "NodeDiedError"}),
            ("train", "failed", {"kind": "diverged", "preset": "fast", "node": "10.0.0.3/cccc", "message": "NaN"}),
            ("train", "finished", {"seconds": 9.0, "preset": "fast-safe", "node": "10.0.0.3/cccc"}),
            ("export", "finished", {"seconds": 1.0, "node": "10.0.0.1/aaaa"})):
        store.log_stage(job.id, stage, "k", event, detail)
    store.finish(job.id, "w", "pass")

    row = json.loads(invoke("summary", "--queue", path, "--json").stdout)["scans"][0]
    assert row["nodes"] == {"process": ["10.0.0.1/aaaa finished"], "export": ["10.0.0.1/aaaa finished"],
                            "train": ["10.0.0.2/bbbb lost", "10.0.0.3/cccc diverged", "10.0.0.3/cccc finished"]}
    lost, diverged = row["failures"]
    assert lost.startswith("train (lost: infrastructure") and "run again as it was" in lost and "on 10.0.0.2/bbbb" in lost
    assert diverged.startswith("train (diverged: the training itself diverged, preset fast, on 10.0.0.3/cccc)")
    printed = invoke("summary", "--queue", path).output
    assert ("stone ran on: process on 10.0.0.1/aaaa; train on 10.0.0.2/bbbb (lost), then 10.0.0.3/cccc (diverged), "
            "then 10.0.0.3/cccc; export on 10.0.0.1/aaaa") in printed
