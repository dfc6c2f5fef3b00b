"""Issue 7's browser criterion: an operator's browser scans, pauses, resumes and opens a report.

Debian's Chromium (/usr/bin/chromium), headless, driven by Playwright, against the dashboard served by
a real uvicorn server on 127.0.0.1 with the simulated rig behind it. `./dev test` installs Chromium
when it can; without it this test is skipped.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest
import uvicorn
from playwright.sync_api import Page, expect, sync_playwright

from station.batch.store import JobStore
from station.cli_serve import make_dashboard
from station.scanfolder import ScanFolder

CHROMIUM = Path("/usr/bin/chromium")
# Playwright adds --headless itself; the rest keep Chromium off this machine's closed network.
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync"]
REPORT = "<!doctype html><html><head><title>pebble-7</title></head><body><h1>PASS: pebble-7</h1></body></html>"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (./dev test installs it as root)"),
]

@dataclass
class Dashboard:
    url: str
    out_dir: Path


def _finished_scan(folder: Path) -> Path:
    """A scan folder as the export stage leaves it; the report's content is the export stage's business."""
    scan = ScanFolder(folder)
    for stage in ("capture", "process", "train", "export"):
        scan.mark_done(stage, {})
    (folder / "asset").mkdir(parents=True)
    (folder / "asset" / "gate.json").write_text(json.dumps({"pass": True, "checks": []}))
    (folder / "asset" / "report.html").write_text(REPORT)
    return folder


@pytest.fixture
def dashboard(tmp_path) -> Iterator[Dashboard]:
    """The dashboard on a free loopback port, in a uvicorn server on a thread; stopped after the test."""
    JobStore(tmp_path / "queue.sqlite").add(_finished_scan(tmp_path / "pebble-7"))
    app = make_dashboard(
        host="127.0.0.1", sim=True, device=None, camera="usb", queue=tmp_path / "queue.sqlite", out_dir=tmp_path / "scans",
        size=(96, 72), time_scale=0.2, elevations=2, azimuths=6, token=None, poll_seconds=0.2,
    )
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, ws="none", access_log=False, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 15
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                raise RuntimeError("the dashboard's server did not start")
            time.sleep(0.05)
        yield Dashboard(f"http://127.0.0.1:{listener.getsockname()[1]}/", tmp_path / "scans")
    finally:
        server.should_exit = True
        thread.join(timeout=45)
        listener.close()
    assert not thread.is_alive(), "the server did not stop"


@pytest.fixture
def page() -> Iterator[Page]:
    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS, headless=True, timeout=30_000)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 960})
            page.set_default_timeout(20_000)
            yield page
        finally:
            browser.close()


def _frames_done(page: Page) -> int:
    return int(page.locator("#progress-text").text_content().split(" of ")[0])


def test_an_operator_scans_pauses_resumes_and_opens_a_finished_scans_report(dashboard, page):
    script_errors: list[str] = []
    page.on("pageerror", lambda error: script_errors.append(str(error)))
    page.goto(dashboard.url)
    expect(page.locator("#rig-label")).to_have_text("simulated rig")
    expect(page.locator("#camera-state")).to_have_text("not connected")
    queued = page.locator("#scans tr", has_text="pebble-7")
    expect(queued.locator(".verdict")).to_have_text("PASS")

    # Start a scan from the form, prefilled with the station's defaults.
    expect(page.locator("#elevations")).to_have_value("2")
    expect(page.locator("#azimuths")).to_have_value("6")
    page.fill("#name", "browser-stone")
    page.click("#start")
    expect(page.locator("#phase")).to_have_text("scanning")
    expect(page.locator("#camera-state")).to_have_text("connected")
    page.wait_for_function("parseInt(document.querySelector('#progress-text').textContent) >= 3")
    page.wait_for_function("document.querySelector('#preview').naturalWidth > 0")
    early_preview = page.locator("#preview").get_attribute("src")

    # Pause: the rig holds still between frames and the count stops.
    page.click("#pause")
    expect(page.locator("#phase")).to_have_text("paused")
    expect(page.locator("#turntable-state")).to_contain_text("holding still")
    held = _frames_done(page)
    page.wait_for_timeout(1000)
    assert _frames_done(page) == held < 14
    assert len(ScanFolder(dashboard.out_dir / "browser-stone").read_manifest()) == held

    # Resume: it runs to the end, and the preview follows the newest frame.
    page.click("#resume")
    expect(page.locator("#phase")).to_have_text("finished", timeout=45_000)
    expect(page.locator("#progress-text")).to_have_text("14 of 14 frames")
    expect(page.locator("#preview")).not_to_have_attribute("src", early_preview)
    page.wait_for_function("document.querySelector('#preview').naturalWidth > 0")
    scanned = page.locator("#scans tr", has_text="browser-stone")
    expect(scanned.locator(".stage.done")).to_have_text("capture ✓")

    # The finished scan's report opens in a tab of its own.
    with page.context.expect_page() as opened:
        queued.get_by_role("link", name="open report").click()
    report = opened.value
    report.wait_for_load_state()
    expect(report.locator("h1")).to_have_text("PASS: pebble-7")
    assert script_errors == []
