"""Untrusted-input corpus: malformed files across process, train, import, sos, export, batch and serve.

Every input must end in a clear error (our "error:" line naming the file or field) and an exit
code of 2 or 3, with no traceback and nothing written outside the folder under test. The CLI runs
in-process (typer's CliRunner) so the corpus is quick; a few cases go through a real subprocess.
"""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

with warnings.catch_warnings():  # Starlette 1.x asks for httpx2 and warns when it finds httpx instead (as test_serve)
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient` is deprecated")
    from fastapi.testclient import TestClient

import corpus_inputs as ci
import corpus_sources as cs
from station.cli import app
from test_import import colmap_world_cameras, ring_cameras, write_colmap, write_idr, write_nerfstudio
from test_trainer import write_sphere_scan

SPLAT_CASES = [ci.Case("sos", f"splat_{name}", ci.splat_case(data), "other.ply") for name, data in ci.SPLAT_PLY_BAD.items()]
CASES = (ci.train_cases() + ci.model_cases("sos") + ci.model_cases("export") + SPLAT_CASES + cs.import_cases()
         + cs.process_cases() + cs.batch_cases() + cs.serve_cli_cases())


def _captured(root: Path) -> None:
    """A captured scan's manifest and raws (the raws are never developed: every case breaks the manifest)."""
    from station.scanfolder import ManifestEntry, ScanFolder, sha256_bytes

    scan = ScanFolder(root)
    entries = []
    for i, (kind, elevation) in enumerate((("plate", 30.0), ("shot", 30.0), ("shot", 30.0))):
        data = f"raw {i}".encode()
        (root / "raw").mkdir(parents=True, exist_ok=True)
        (root / "raw" / f"e0_a{i:03d}.dng").write_bytes(data)
        entries.append(ManifestEntry(f"raw/e0_a{i:03d}.dng", sha256_bytes(data), elevation, 9.0 * i, kind, 0.01, 100, ""))
    scan.write_manifest(entries)
    scan.mark_done("capture", {})


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> ci.Bases:
    root = tmp_path_factory.mktemp("bases")
    posed, trained = root / "posed", root / "trained"
    write_sphere_scan(posed)
    ci.copy_base(posed, trained)
    (trained / "model").mkdir()
    torch.save(ci.surface_state(), trained / "model" / "surface.pt")
    torch.save({"means": torch.zeros(4, 3), "scales": torch.full((4,), 0.05), "levels": torch.full((4,), 8)},
               trained / "model" / "infill.pt")
    _captured(root / "captured")
    write_nerfstudio(root / "nerfstudio", ring_cameras(count=3))
    write_colmap(root / "colmap", colmap_world_cameras()[0])
    cams = [np.block([[c[:3, :3], 1000.0 * c[:3, 3:]], [np.array([[0, 0, 0, 1.0]])]]) for c in ring_cameras(count=4)]
    write_idr(root / "idr", cams)
    return ci.Bases(posed, trained, root / "captured", root / "nerfstudio", root / "colmap", root / "idr")


def snapshot(root: Path, skip: Path) -> dict[str, tuple]:
    """Every entry under `root` except `skip`, links not followed: what a case must leave unchanged."""
    seen = {}
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        dirs[:] = [d for d in dirs if here / d != skip]
        for name in dirs + files:
            stat = (here / name).lstat()
            seen[str(here / name)] = (stat.st_size, stat.st_mtime_ns, stat.st_mode)
    return seen


def invoke(argv: list[str]):
    """The CLI in-process; the logging handlers a command installs are removed again (they hold its stderr)."""
    handlers = list(logging.root.handlers)
    try:
        return CliRunner().invoke(app, argv)
    finally:
        logging.root.handlers[:] = handlers


def assert_clear_error(result, names: str) -> None:
    output = result.output.replace("\n", "")
    assert "Traceback" not in output, output[-600:]
    assert result.exception is None or isinstance(result.exception, SystemExit), f"uncaught {result.exception!r}"
    assert result.exit_code in (2, 3), f"exit code {result.exit_code}: {output[-600:]}"
    assert "error:" in output and names in output, output[-600:]


@pytest.fixture
def refuse_real_work(monkeypatch):
    """An input that reaches training or scoring was not refused: that fails at once instead of running the stage."""
    import station.export.stage as export_stage
    import station.ngs.sos as sos
    from station.ngs.trainer import Trainer

    def accepted(*args, **kwargs):
        pytest.fail("a malformed input was accepted: the stage went on to its real work")

    monkeypatch.setattr(Trainer, "train_step", accepted)
    monkeypatch.setattr(sos, "evaluate", accepted)
    monkeypatch.setattr(export_stage, "evaluate", accepted)


@pytest.fixture
def sandbox(tmp_path, monkeypatch, refuse_real_work):
    """(case folder, outside folder): the working directory and `outside` are watched for writes."""
    for name in ("STATION_QUEUE", "STATION_RIG_MODEL", "STATION_TOKEN"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / "cwd").mkdir()
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "keep.txt").write_text("not yours")
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path / "case", tmp_path / "outside"


def run_case(case: ci.Case, sandbox, bases: ci.Bases) -> None:
    folder, outside = sandbox
    argv = case.build(folder, outside, bases)
    before = snapshot(folder.parent, folder)
    result = invoke(argv)
    assert snapshot(folder.parent, folder) == before, "a write outside the folder under test"
    assert_clear_error(result, case.names)


@pytest.mark.parametrize("case", CASES, ids=[f"{c.command}-{c.name}" for c in CASES])
def test_each_malformed_input_gives_a_clear_error_and_writes_nothing_outside(case, sandbox, bases, monkeypatch):
    import uvicorn

    monkeypatch.setattr(uvicorn, "run", lambda *a, **k: pytest.fail("a malformed serve option reached uvicorn.run"))
    run_case(case, sandbox, bases)


BAD_NUMBERS = st.one_of(st.sampled_from([0, -1, 1e-30, True, False, None, "abc", [1], {}, math.nan, math.inf, -math.inf]),
                        st.floats(max_value=0.0, allow_nan=False), st.floats(min_value=1e9, allow_infinity=False))
NOT_ROTATIONS = st.one_of(
    st.floats(0.0, 0.98).map(lambda s: np.diag([s, s, s, 1.0])), st.floats(1.02, 1e3).map(lambda s: np.diag([s, 1.0, 1.0, 1.0])),
    st.sampled_from([np.diag([1.0, 1.0, -1.0, 1.0]), np.diag([-1.0, 1.0, 1.0, 1.0]), np.zeros((4, 4))]),
    st.lists(st.floats(-5, 5), min_size=12, max_size=12).map(lambda v: np.vstack([np.reshape(v, (3, 4)), [0, 0, 0, 1.0]])),
)
MALFORMED_TRANSFORMS = st.one_of(
    st.tuples(st.sampled_from(["fl_x", "fl_y"]), BAD_NUMBERS).map(lambda kv: ((kv[0],), kv[1])),
    st.tuples(st.sampled_from(["w", "h"]), st.one_of(BAD_NUMBERS, st.integers(max_value=0), st.integers(min_value=70_000),
                                                     st.floats(1.1, 999.9).filter(lambda v: v != int(v)))).map(lambda kv: ((kv[0],), kv[1])),
    st.tuples(st.integers(0, 7), NOT_ROTATIONS).map(lambda iv: (("frames", iv[0], "transform_matrix"), iv[1].tolist())),
    st.tuples(st.integers(0, 7), st.sampled_from(["file_path", "mask_path"]),
              st.sampled_from([5, 1.5, True, [], {}, "../x.png", "/etc/hostname", "images/none.png"])).map(
        lambda t: (("frames", t[0], t[1]), t[2])),
)


@pytest.mark.slow
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(MALFORMED_TRANSFORMS)
def test_generated_malformed_transforms_stop_train_with_a_clear_error(bases, tmp_path_factory, refuse_real_work, change):
    keys, value = change
    folder = tmp_path_factory.mktemp("generated") / "case"
    ci.copy_base(bases.posed, folder)
    ci.edit_json(folder / "poses" / "transforms.json", lambda d: ci.set_path(d, keys, value))
    before = snapshot(folder.parent, folder)
    assert_clear_error(invoke(["train", str(folder)]), "transforms.json")
    assert snapshot(folder.parent, folder) == before


def _queued_scan_with_gate(folder: Path, outside: Path, spoil) -> Path:
    from station.batch.store import JobStore

    scan = folder / "scan"
    (scan / "stages").mkdir(parents=True)
    (scan / "stages" / "capture.json").write_text("{}")
    (scan / "asset").mkdir()
    spoil(scan / "asset" / "gate.json", outside)
    JobStore(folder / "queue.sqlite").add(scan)
    return folder / "queue.sqlite"


@pytest.mark.parametrize("name", sorted(cs.GATE_BAD))
def test_the_dashboard_shows_a_malformed_gate_verdict_as_an_error_not_a_crash(name, sandbox):
    from station.cli_serve import make_dashboard

    folder, outside = sandbox
    folder.mkdir()
    queue = _queued_scan_with_gate(folder, outside, cs.GATE_BAD[name])
    before = snapshot(folder.parent, folder)
    app_ = make_dashboard(host="127.0.0.1", sim=False, device=None, camera="usb", queue=queue, out_dir=folder / "scans",
                          size=(320, 240), time_scale=0.05, elevations=6, azimuths=40, token=None)
    with TestClient(app_, base_url="http://127.0.0.1:8000") as client:
        rows = client.get("/api/queue").json()["scans"]
        report = client.get(f"/scans/{rows[0]['key']}/report")
    assert rows[0]["gate"]["pass"] is None and "gate.json" in rows[0]["gate"]["error"]
    assert report.status_code == 404 and "error" in report.json()
    assert snapshot(folder.parent, folder) == before


@pytest.mark.parametrize("spoil", ["garbage", "broken_page"])
def test_the_dashboard_answers_a_malformed_queue_with_an_error(spoil, sandbox):
    from station.cli_serve import make_dashboard

    folder, _ = sandbox
    folder.mkdir()
    if spoil == "garbage":
        ci.garbage(folder / "queue.sqlite", 8192)
    else:
        scans = []
        for i in range(40):
            (folder / f"s{i}" / "stages").mkdir(parents=True)
            scans.append(folder / f"s{i}")
        cs.corrupt_page(cs.queue_with(folder, scans))
    app_ = make_dashboard(host="127.0.0.1", sim=False, device=None, camera="usb", queue=folder / "queue.sqlite",
                          out_dir=folder / "scans", size=(320, 240), time_scale=0.05, elevations=6, azimuths=40, token=None)
    with TestClient(app_, base_url="http://127.0.0.1:8000", raise_server_exceptions=True) as client:
        answer = client.get("/api/queue")
    assert answer.status_code in (400, 409, 422, 500, 503) and "queue.sqlite" in answer.json()["error"]


SUBPROCESS_CASES = ["train-checkpoint_empty", "process-manifest_not_utf8", "import-nerfstudio_nested_100k",
                    "batch-broken_page_status"]


@pytest.mark.slow
@pytest.mark.parametrize("case_id", SUBPROCESS_CASES)
def test_a_real_process_prints_one_error_line_and_no_traceback(case_id, sandbox, bases):
    case = next(c for c in CASES if f"{c.command}-{c.name}" == case_id)
    folder, outside = sandbox
    argv = case.build(folder, outside, bases)
    before = snapshot(folder.parent, folder)
    proc = subprocess.run([sys.executable, "-m", "station", *argv], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "400"})
    assert snapshot(folder.parent, folder) == before
    assert proc.returncode in (2, 3) and "Traceback" not in proc.stderr and "Aborted" not in proc.stderr, proc.stderr[-800:]
    assert "error:" in proc.stderr and case.names in proc.stderr


def test_the_corpus_holds_over_a_hundred_inputs_across_every_command():
    counts = Counter(c.command for c in CASES)
    counts["serve"] += len(cs.GATE_BAD) + 2  # the dashboard tests above
    sys.stdout.write(json.dumps(dict(sorted(counts.items()))) + "\n")
    assert set(counts) == {"process", "train", "import", "sos", "export", "batch", "serve"}
    assert sum(counts.values()) >= 100 and min(counts.values()) >= 8
