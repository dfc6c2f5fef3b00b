"""bench/report.py: docs/evidence.md is generated from every committed results file, plots and all."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.no_kernels

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def run_report(results: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "report.py"), "--results", str(results),
                           "--out", str(out)], capture_output=True, text=True, timeout=120)


@pytest.fixture
def results_copy(tmp_path: Path) -> Path:
    copy = tmp_path / "bench" / "results"
    copy.mkdir(parents=True)
    for path in RESULTS.glob("*.json"):
        shutil.copy(path, copy)
    for pattern in ("ngs*.svg", "real_*.svg", "plans*.svg"):  # drawn by their bench scripts, not by the report
        for path in RESULTS.glob(pattern):
            shutil.copy(path, copy)
    return copy


def test_every_committed_results_file_has_a_section_and_every_link_resolves(results_copy: Path, tmp_path: Path):
    out = tmp_path / "docs" / "evidence.md"
    done = run_report(results_copy, out)
    assert done.returncode == 0, done.stderr
    page = out.read_text()
    committed = sorted(p.name for p in RESULTS.glob("*.json"))
    assert committed
    for name in committed:
        assert f"### {name}" in page and f"bench/results/{name}" in page, name
    links = re.findall(r"\]\(([^)]+)\)", page)
    assert any(link.endswith(".svg") for link in links)
    for link in links:
        assert (out.parent / link).resolve().is_file(), link
    for svg in results_copy.glob("*.svg"):
        assert ET.parse(svg).getroot().tag.endswith("svg"), svg.name


def test_a_results_file_of_an_unknown_bench_still_gets_its_figures(results_copy: Path, tmp_path: Path):
    (results_copy / "zz_new_bench.json").write_text(json.dumps({"benchmark": "new", "wall_s": 12.5, "rows": []}))
    out = tmp_path / "evidence.md"
    done = run_report(results_copy, out)
    assert done.returncode == 0, done.stderr
    section = out.read_text().split("### zz_new_bench.json", 1)[1]
    assert "| wall_s | 12.500 |" in section and "`rows`" in section


def test_real_photos_open_with_every_ngs_run_on_a_scan_and_the_spread_of_its_sos(results_copy: Path, tmp_path: Path):
    scan = "a test scan"
    for name, seed, sos in (("real_a.json", 0, 0.93), ("real_b.json", 1, 0.97), ("real_c.json", 2, 0.95)):
        run = {"psnr": 31.5, "psnr_star": 31.5, "ssim": 0.97, "sos": sos, "num_gaussians": 60000, "steps": 5000,
               "planned_steps": 2500, "train_seconds": 300.0 + seed, "held_out_curve": [{"step": 2500, "sos": sos}]}
        (results_copy / name).write_text(json.dumps({"benchmark": "real", "scan": scan, "presets": ["fast"],
                                                     "seed": seed, "peer": "none", "methods": {"ngs": run},
                                                     "ngs_psnr_gap_to_best_db": None}))
    out = tmp_path / "evidence.md"
    done = run_report(results_copy, out)
    assert done.returncode == 0, done.stderr
    summary = out.read_text().split("## NGS on real photos", 1)[1].split("###", 1)[0]
    ours = summary.split(f"NGS on {scan}: every run", 1)[1].split("NGS on ", 1)[0]
    assert [line.split(" | ")[0] for line in ours.splitlines() if line.startswith("| real_")] == \
        ["| real_a.json", "| real_b.json", "| real_c.json"]
    assert "Over these 3 runs: SOS median 0.950, range 0.930 to 0.970; train s 300 to 302." in ours


def test_a_broken_results_file_is_named_without_a_traceback(results_copy: Path, tmp_path: Path):
    (results_copy / "broken.json").write_text('{"benchmark": ')
    out = tmp_path / "evidence.md"
    done = run_report(results_copy, out)
    assert done.returncode != 0
    assert "broken.json" in done.stderr and "Traceback" not in done.stderr
    assert not out.exists()


def test_the_committed_evidence_page_is_the_one_the_committed_results_give(results_copy: Path, tmp_path: Path):
    out = tmp_path / "docs" / "evidence.md"
    done = run_report(results_copy, out)
    assert done.returncode == 0, done.stderr
    assert out.read_text() == (ROOT / "docs" / "evidence.md").read_text(), \
        "docs/evidence.md is stale: run ./dev bench report and commit the page and its plots"
