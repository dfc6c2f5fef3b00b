"""`station serve`'s JSON API, as the page and an operator's script use it.

Scans run on the simulated rig through the same wiring as `station scan --sim`. The dashboard binds
loopback unless a token guards it, refuses buttons that do not fit the rig's state, and serves a
report only for a scan it knows, from inside that scan's folder.
"""

from __future__ import annotations

import io
import json
import time
import warnings
from pathlib import Path
from typing import Callable, Iterator

import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from station.batch.store import JobStore
from station.cli_serve import make_dashboard, serve
from station.errors import BadInputError
from station.scanfolder import ScanFolder
from station.serve.scans import scan_key

with warnings.catch_warnings():  # Starlette 1.x asks for httpx2 and warns when it finds httpx instead
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient` is deprecated")
    from fastapi.testclient import TestClient

TOKEN = "correct-horse-battery-staple"
LOOPBACK = "http://127.0.0.1"


def _app(tmp_path: Path, **overrides):
    options = dict(
        host="127.0.0.1", sim=True, device=None, camera="usb", queue=tmp_path / "queue.sqlite",
        out_dir=tmp_path / "scans", size=(96, 72), time_scale=0.05, elevations=2, azimuths=12, token=None,
    )
    options.update(overrides)
    return make_dashboard(**options)


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    """A dashboard on the simulated rig; leaving it cancels any scan still running and waits for it."""
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as test_client:
        yield test_client


def wait_for(client: TestClient, condition: Callable[[dict], bool], timeout_s: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        state = client.get("/api/state").json()
        if condition(state):
            return state
        if time.monotonic() > deadline:
            raise AssertionError(f"state never matched: {json.dumps(state)}")
        time.sleep(0.02)


def phase(name: str) -> Callable[[dict], bool]:
    return lambda state: state["scan"] is not None and state["scan"]["phase"] == name


def frames_done(at_least: int) -> Callable[[dict], bool]:
    return lambda state: state["scan"] is not None and state["scan"]["done"] >= at_least


def prompt_says(text: str) -> Callable[[dict], bool]:
    return lambda state: text in (state["operator_prompt"] or "")


def start(client: TestClient, name: str = "stone-1", **fields) -> dict:
    response = client.post("/api/scan/start", json={"name": name, "elevations": 2, "azimuths": 12, **fields})
    assert response.status_code == 200, response.text
    return response.json()


def manifest_count(tmp_path: Path, name: str) -> int:
    return len(ScanFolder(tmp_path / "scans" / name).read_manifest())


# -- the rig and the scan buttons ------------------------------------------------------------------
def test_an_idle_dashboard_shows_the_rig_disconnected_and_the_form_defaults(client):
    state = client.get("/api/state").json()
    assert state["rig"]["label"] == "simulated rig" and state["rig"]["connected"] is False
    assert state["rig"]["camera"] == "not connected"
    assert state["scan"] is None and state["operator_prompt"] is None
    assert state["defaults"] == {"elevations": 2, "azimuths": 12}


def test_a_started_scan_shows_progress_the_rig_pose_and_a_preview_until_it_finishes(client, tmp_path):
    start(client)
    moving = wait_for(client, frames_done(3))
    assert moving["rig"]["connected"] is True and moving["rig"]["camera"] == "connected"
    assert moving["rig"]["turntable"]["elevation_deg"] is not None
    assert moving["scan"]["total"] == 2 + 2 * 12 and moving["scan"]["latest"].startswith("raw/")

    preview = client.get("/api/scan/preview.jpg")
    assert preview.status_code == 200 and preview.headers["content-type"] == "image/jpeg"
    assert Image.open(io.BytesIO(preview.content)).size == (48, 36), "a half-size develop of the 96x72 raw"

    finished = wait_for(client, phase("finished"))["scan"]
    assert finished["done"] == finished["total"] == finished["shot_now"] == 26 and finished["kept"] == 0
    row = next(r for r in client.get("/api/queue").json()["scans"] if r["name"] == "stone-1")
    assert row["source"] == "dashboard" and row["stages"]["capture"] is True and row["report_url"] is None


def test_pause_holds_the_rig_between_frames_until_resume(client, tmp_path):
    start(client)
    wait_for(client, frames_done(2))
    assert client.post("/api/scan/pause", json={}).status_code == 200
    paused = wait_for(client, phase("paused"))
    assert paused["rig"]["turntable"]["state"] == "holding still at the pose (paused)"
    time.sleep(0.5)
    still = client.get("/api/state").json()["scan"]
    assert still["phase"] == "paused" and still["done"] == paused["scan"]["done"] < still["total"]
    assert manifest_count(tmp_path, "stone-1") == still["done"], "every frame counted is on disk, no more"

    assert client.post("/api/scan/resume", json={}).status_code == 200
    assert wait_for(client, phase("finished"))["scan"]["done"] == still["total"]


def test_cancel_stops_at_a_frame_boundary_and_starting_the_same_scan_again_resumes_it(client, tmp_path):
    request = start(client)["scan"]["request"]
    wait_for(client, frames_done(2))
    client.post("/api/scan/pause", json={})
    wait_for(client, phase("paused"))
    assert client.post("/api/scan/cancel", json={}).status_code == 200
    cancelled = wait_for(client, phase("cancelled"))["scan"]
    assert cancelled["resumable"] is True and "kept" in cancelled["message"]
    assert cancelled["done"] == manifest_count(tmp_path, "stone-1") < cancelled["total"]
    assert client.get("/api/state").json()["rig"]["connected"] is False

    assert client.post("/api/scan/start", json=request).status_code == 200
    resumed = wait_for(client, phase("finished"))["scan"]
    assert resumed["kept"] == cancelled["done"] and resumed["shot_now"] == resumed["total"] - cancelled["done"]


def test_buttons_that_do_not_fit_the_rig_state_are_refused_as_conflicts(client):
    for button in ("pause", "resume", "cancel"):
        refused = client.post(f"/api/scan/{button}", json={})
        assert refused.status_code == 409 and "no scan is running" in refused.json()["error"]
    start(client)
    second = client.post("/api/scan/start", json={"name": "stone-2", "elevations": 1, "azimuths": 1})
    assert second.status_code == 409 and "stone-1 is still running" in second.json()["error"]
    assert client.post("/api/scan/resume", json={}).status_code == 409, "resume only what is paused"
    assert client.post("/api/operator/done", json={}).status_code == 409, "the simulated operator never asks"


@pytest.mark.parametrize("body, status, why", [
    ({"name": "../escape", "elevations": 2, "azimuths": 6}, 400, "scan name"),
    ({"name": ".hidden", "elevations": 2, "azimuths": 6}, 400, "scan name"),
    ({"name": "s", "elevations": 0, "azimuths": 6}, 400, "elevations"),
    ({"name": "s", "elevations": 2, "azimuths": 6, "stone": "/etc/passwd"}, 400, "stone"),
    ({"name": "s", "elevations": 2, "azimuths": 6, "azimuth": 9}, 422, "extra"),
])
def test_a_bad_scan_request_is_refused_before_any_folder_is_made(client, tmp_path, body, status, why):
    refused = client.post("/api/scan/start", json=body)
    assert refused.status_code == status and why in refused.text
    assert not (tmp_path / "scans").exists() and not (tmp_path / "escape").exists()


def test_without_a_rig_the_dashboard_shows_the_queue_but_cannot_scan(tmp_path):
    with TestClient(_app(tmp_path, sim=False), base_url=LOOPBACK) as client:
        assert client.get("/api/state").json()["rig"]["label"].startswith("no rig")
        assert client.get("/api/queue").status_code == 200
        refused = client.post("/api/scan/start", json={"name": "s", "elevations": 1, "azimuths": 1})
        assert refused.status_code == 409 and "--sim or --device" in refused.json()["error"]


# -- who may use it ---------------------------------------------------------------------------------
@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20", "::"])
def test_a_non_loopback_host_is_refused_without_a_token(tmp_path, host):
    with pytest.raises(BadInputError, match="STATION_TOKEN"):
        _app(tmp_path, host=host)


def test_the_serve_command_exits_2_rather_than_listen_beyond_loopback_without_a_token(tmp_path):
    cli = typer.Typer()
    cli.callback()(lambda: None)
    cli.command("serve")(serve)
    result = CliRunner().invoke(cli, ["serve", "--sim", "--host", "0.0.0.0", "--out-dir", str(tmp_path)],
                                env={"STATION_TOKEN": ""})
    assert result.exit_code == 2 and "STATION_TOKEN" in result.output


def test_a_short_token_is_refused(tmp_path):
    with pytest.raises(BadInputError, match="too short"):
        _app(tmp_path, host="0.0.0.0", token="1234")


GUARDED = [
    ("get", "/api/state"), ("get", "/api/queue"), ("get", "/api/scan/preview.jpg"), ("post", "/api/scan/start"),
    ("post", "/api/scan/pause"), ("post", "/api/scan/resume"), ("post", "/api/scan/cancel"),
    ("post", "/api/operator/done"), ("get", "/scans/0123456789abcdef/report"),
]


@pytest.mark.parametrize("method, path", GUARDED)
@pytest.mark.parametrize("offered", [None, "Bearer wrong-token-wrong-token", "Basic " + TOKEN])
def test_with_a_token_every_route_that_reads_scans_or_moves_the_rig_refuses_without_it(tmp_path, method, path, offered):
    headers = {"Authorization": offered} if offered else {}
    client = TestClient(_app(tmp_path, host="0.0.0.0", token=TOKEN), base_url="http://station.lan:8000")
    response = getattr(client, method)(path, headers=headers)
    assert response.status_code == 401 and "token" in response.json()["detail"]
    assert not (tmp_path / "scans").exists()


def test_with_a_token_the_page_loads_and_the_token_opens_the_api_as_header_or_cookie(tmp_path):
    client = TestClient(_app(tmp_path, host="0.0.0.0", token=TOKEN), base_url="http://station.lan:8000")
    page = client.get("/")
    assert page.status_code == 200 and "/static/dashboard.js" in page.text
    assert client.get("/api/state", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    client.cookies.set("station_token", TOKEN)
    assert client.get("/api/queue").status_code == 200


def test_on_loopback_a_foreign_host_name_is_refused_so_dns_rebinding_cannot_reach_the_rig(client):
    refused = client.get("/api/state", headers={"Host": "rebound.example:8000"})
    assert refused.status_code == 403
    assert client.get("/api/state", headers={"Host": "localhost:8000"}).status_code == 200


def test_a_button_pressed_from_another_origin_is_refused(client):
    refused = client.post("/api/scan/start", json={"name": "s", "elevations": 1, "azimuths": 1},
                          headers={"Origin": "http://evil.example"})
    assert refused.status_code == 403 and "another origin" in refused.json()["detail"]
    assert client.get("/api/state").json()["scan"] is None


def test_a_button_pressed_by_a_cross_site_form_without_origin_is_refused(client):
    form = client.post("/api/scan/start", content="name=s&elevations=1&azimuths=1",
                       headers={"Content-Type": "application/x-www-form-urlencoded"})
    assert form.status_code == 403 and "JSON body" in form.json()["detail"]
    assert client.get("/api/state").json()["scan"] is None


# -- the queue, its verdicts and reports ------------------------------------------------------------
def _exported_scan(folder: Path, passed: bool, report: str | None = "<!doctype html><title>r</title><h1>PASS</h1>") -> Path:
    """A scan folder as export leaves it: stage markers, gate.json and (optionally) report.html."""
    scan = ScanFolder(folder)
    for stage in ("capture", "process", "train", "export"):
        scan.mark_done(stage, {})
    checks = [{"name": "sos", "value": 0.97 if passed else 0.4, "threshold": 0.9, "pass": passed,
               "reason": "" if passed else "SOS 0.400 < 0.9: the model is see-through"}]
    (folder / "asset").mkdir(parents=True)
    (folder / "asset" / "gate.json").write_text(json.dumps({"pass": passed, "checks": checks}))
    if report is not None:
        (folder / "asset" / "report.html").write_text(report)
    return folder


def _queue(tmp_path: Path, *folders: Path) -> JobStore:
    store = JobStore(tmp_path / "queue.sqlite")
    for folder in folders:
        store.add(folder)
    return store


def test_the_queue_lists_each_scan_with_its_job_stages_gate_verdict_and_report_link(tmp_path):
    good = _exported_scan(tmp_path / "good", passed=True)
    bad = _exported_scan(tmp_path / "bad", passed=False, report=None)
    waiting = tmp_path / "waiting"
    store = _queue(tmp_path, good, bad, waiting)
    job = store.claim("worker-1")
    store.finish(job.id, "worker-1", verdict="pass")
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        rows = {row["name"]: row for row in client.get("/api/queue").json()["scans"]}
    assert list(rows) == ["good", "bad", "waiting"]
    assert rows["good"]["job"]["state"] == "done" and rows["good"]["job"]["verdict"] == "pass"
    assert rows["good"]["gate"] == {"pass": True, "failed": []}
    assert rows["good"]["report_url"] == f"/scans/{scan_key(good)}/report"
    assert rows["bad"]["gate"] == {"pass": False, "failed": ["SOS 0.400 < 0.9: the model is see-through"]}
    assert rows["bad"]["report_url"] is None
    assert rows["waiting"]["job"]["state"] == "queued" and rows["waiting"]["gate"] is None
    assert not any(rows["waiting"]["stages"].values())


def test_the_dashboard_never_creates_a_queue_but_shows_one_made_after_it_started(tmp_path):
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        empty = client.get("/api/queue").json()
        assert empty["queue_exists"] is False and empty["scans"] == []
        assert not (tmp_path / "queue.sqlite").exists()
        _queue(tmp_path, _exported_scan(tmp_path / "late", passed=True))
        later = client.get("/api/queue").json()
    assert later["queue_exists"] is True and [row["name"] for row in later["scans"]] == ["late"]


def test_a_malformed_gate_file_shows_as_unreadable_instead_of_breaking_the_page(tmp_path):
    folder = _exported_scan(tmp_path / "odd", passed=True)
    (folder / "asset" / "gate.json").write_text('{"pass": "yes"')
    _queue(tmp_path, folder)
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        gate = client.get("/api/queue").json()["scans"][0]["gate"]
    assert gate["pass"] is None and "not valid JSON" in gate["error"]


def test_a_queued_scans_report_is_served_sandboxed(tmp_path):
    good = _exported_scan(tmp_path / "good", passed=True)
    _queue(tmp_path, good)
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        report = client.get(f"/scans/{scan_key(good)}/report")
    assert report.status_code == 200 and "<h1>PASS</h1>" in report.text
    assert report.headers["content-type"].startswith("text/html")
    assert report.headers["content-security-policy"].startswith("sandbox;"), "a scan folder's HTML is untrusted"


def test_a_report_is_refused_for_any_folder_the_queue_and_dashboard_do_not_know(tmp_path):
    _queue(tmp_path, _exported_scan(tmp_path / "good", passed=True))
    stranger = _exported_scan(tmp_path / "stranger", passed=True)
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        for path in (f"/scans/{scan_key(stranger)}/report", "/scans/..%2Fstranger/report",
                     "/scans/../stranger/asset/report.html", "/scans/0123456789abcdef/report"):
            refused = client.get(path)
            assert refused.status_code == 404, path
            assert "<h1>PASS</h1>" not in refused.text


def test_a_report_that_links_outside_its_scan_folder_is_refused(tmp_path):
    secret = tmp_path / "secret.html"
    secret.write_text("station secrets")
    folder = _exported_scan(tmp_path / "sly", passed=True, report=None)
    (folder / "asset" / "report.html").symlink_to(secret)
    _queue(tmp_path, folder)
    with TestClient(_app(tmp_path), base_url=LOOPBACK) as client:
        assert client.get("/api/queue").json()["scans"][0]["report_url"] is None
        refused = client.get(f"/scans/{scan_key(folder)}/report")
    assert refused.status_code == 403 and "outside the scan folder" in refused.json()["error"]
    assert "station secrets" not in refused.text


# -- a hardware rig: the emulated GRBL board on a port, the simulated camera -------------------------
def test_on_a_hardware_rig_the_operator_is_asked_on_the_page_and_the_scan_waits_for_done(tmp_path):
    from sim.grbl_links import start_fake_turntable

    with start_fake_turntable("url", time_scale=0.02) as board:
        app = _app(tmp_path, sim=False, device=board.port, camera="sim")
        with TestClient(app, base_url=LOOPBACK) as client:
            assert board.port in client.get("/api/state").json()["rig"]["label"]
            start(client, elevations=1, azimuths=3)
            for expected in ("Remove the stone", "Place the stone"):
                asking = wait_for(client, prompt_says(expected))
                assert asking["scan"]["phase"] == "waiting for operator"
                time.sleep(0.2)
                assert client.get("/api/state").json()["operator_prompt"] == asking["operator_prompt"], "it waits"
                assert client.post("/api/operator/done", json={}).status_code == 200
            finished = wait_for(client, phase("finished"))["scan"]
    assert finished["done"] == finished["total"] == 4
