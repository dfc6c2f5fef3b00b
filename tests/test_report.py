"""The HTML report: self-contained, verdict first, readable figures, curves drawn inline."""

from __future__ import annotations

import base64
import re

import cv2
import numpy as np
import pytest
import torch

from station.export.gate import GateConfig, evaluate_gate
from station.ngs.dataset import View
from station.export.report import (
    HeldOutPanel,
    Panels,
    ReportInputs,
    build_report_html,
    crop_box,
    png_data_uri,
    svg_curve,
    transmittance_picture,
    write_report,
)

pytestmark = pytest.mark.no_kernels

GOOD = {"sos": 0.97, "psnr": 33.2, "ssim": 0.95, "psnr_star": 33.1, "ssim_star": 0.95, "lpips": "skipped",
        "num_gaussians": 12000, "num_infill": 1700, "train_seconds": 812.5, "mesh_watertight": True,
        "mesh_manifold": True, "mesh_problems": [], "mesh_volume_m3": 1.1e-4, "infill_volume_m3": 1.08e-4,
        "mesh_area_m2": 0.0148, "outside_hull_fraction": 0.0,
        "views": [{"view": "v000.png", "psnr": 33.0, "sos": 0.97}]}


def panels() -> Panels:
    rng = np.random.default_rng(0)
    image = rng.random((12, 16, 3))
    held = HeldOutPanel("v000.png", image, image, image, np.full((12, 16), 1e-3))
    return Panels(held_out=[held], strip=[("v001.png", image, image), ("v002.png", image, image)])


def report(metrics: dict, train: dict | None = None) -> str:
    gate = evaluate_gate(metrics, GateConfig())
    return build_report_html(ReportInputs("stone-42", metrics, gate, train or {}, panels()))


def test_a_passing_scan_says_pass_first_in_green():
    text = report(GOOD)
    assert text.index("PASS") < text.index("Quality checks")
    assert 'class="verdict pass"' in text and "QUARANTINED" not in text


def test_a_failing_scan_says_quarantined_with_each_reason():
    text = report({**GOOD, "sos": 0.3, "mesh_watertight": False, "mesh_problems": ["mesh has holes (not watertight)"]})
    verdict = text[text.index('class="verdict fail"'):text.index("Quality checks")]
    assert "QUARANTINED" in verdict
    assert "SOS 0.300 &lt; 0.9" in verdict and "see-through" in verdict
    assert "mesh has holes" in verdict
    assert "PASS" not in verdict


def test_the_report_embeds_every_image_and_links_nothing_outside():
    text = report(GOOD, {"losses": [{"step": 100, "loss": 0.2}, {"step": 200, "loss": 0.1}]})
    assert "http://" not in text and "https://" not in text and "<script" not in text and "<link" not in text
    sources = re.findall(r'src="([^"]*)"', text)
    assert len(sources) == 4 + 2 * 2  # held-out row of four, strip of photos and renders
    for source in sources:
        assert source.startswith("data:image/png;base64,")
        data = np.frombuffer(base64.b64decode(source.split(",", 1)[1]), np.uint8)
        assert cv2.imdecode(data, cv2.IMREAD_UNCHANGED).shape[:2] == (12, 16)


def test_figures_carry_units_and_missing_ones_say_so():
    text = report({**GOOD, "train_seconds": None})
    assert "dB" in text and "m³" in text and "m²" in text
    row = re.search(r"<tr><td>train_seconds</td><td>([^<]*)</td>", text)
    assert row and row.group(1) == "not measured"


def test_training_curves_are_inline_polylines_and_absent_held_out_error_is_explained():
    losses = [{"step": s, "seconds": s / 10, "loss": 1.0 / s, "image": 0.5 / s} for s in range(100, 1100, 100)]
    text = report(GOOD, {"losses": losses})
    assert text.count("<polyline") == 2  # loss and image, not the seconds column
    assert "Held-out error was not recorded" in text
    held_out = [{"step": 500, "psnr": 28.0, "sos": None}, {"step": 1000, "psnr": 31.0, "sos": 0.91},
                {"step": 1500, "psnr": 31.1, "sos": 0.95}]
    with_eval = report(GOOD, {"losses": losses, "held_out": held_out, "planned_steps": 1000, "extensions": [
        {"step": 1000, "extend": True, "reason": "SOS 0.910 below 0.95 and still rising"},
        {"step": 1500, "extend": False, "reason": "SOS 0.950 reached 0.95, PSNR flat"}]})
    assert with_eval.count("<polyline") == 4  # losses, held-out PSNR and held-out SOS
    assert "Planned 1000 steps, trained 1500" in with_eval and "SOS 0.910 below 0.95 and still rising" in with_eval
    ended = report(GOOD, {"losses": losses, "held_out": held_out, "planned_steps": 2500, "extensions": [
        {"step": 1500, "extend": False, "finished_early": True, "reason": "SOS 0.995 reached 0.99"}]})
    assert "Planned 2500 steps, ended at step 1500: SOS 0.995 reached 0.99" in ended
    sh = {"trained": 1, "kept": 0, "tolerance_db": 0.1, "held_out_psnr": {"0": 41.2, "1": 41.25}}
    with_sh = report(GOOD, {"losses": losses, "sh_degree": sh})
    assert "written at degree 0" in with_sh and "41.20 dB at degree 0, 41.25 dB at degree 1" in with_sh
    resolution = {"start_downscale": 2, "final_downscale": 1, "checks": [
        {"step": 100, "downscale": 2, "psnr": 32.5, "move_up": False, "reason": "first check at this level"},
        {"step": 200, "downscale": 2, "psnr": 31.9, "move_up": True, "reason": "gained -0.60 dB"}]}
    with_resolution = report(GOOD, {"losses": losses, "resolution": resolution})
    assert "trained at 1/2 until step 200 (gained -0.60 dB), then at full resolution" in with_resolution


def test_a_curve_maps_its_extremes_to_the_plot_edges_and_skips_non_numbers():
    svg = svg_curve([0, 1, 2, 3], [4.0, float("nan"), 2.0, 1.0], "loss", "", width=200, height=100)
    points = re.search(r'points="([^"]*)"', svg).group(1).split()
    assert len(points) == 3
    xs = [float(p.split(",")[0]) for p in points]
    ys = [float(p.split(",")[1]) for p in points]
    assert xs[0] == pytest.approx(30) and xs[-1] == pytest.approx(170)
    assert ys[0] == pytest.approx(30) and ys[-1] == pytest.approx(70)  # max at the top, min at the bottom
    assert "fewer than two points" in svg_curve([0], [1.0], "loss", "")


def test_transmittance_is_shown_on_a_log_scale():
    shown = transmittance_picture(np.array([0.0, 1e-6, 1e-3, 1.0]))
    np.testing.assert_allclose(shown, [0.0, 0.0, 0.5, 1.0], atol=1e-9)


def test_png_data_uris_round_trip_colour_and_grey():
    rgb = np.zeros((2, 3, 3))
    rgb[0, 0] = [1.0, 0.0, 0.0]
    data = np.frombuffer(base64.b64decode(png_data_uri(rgb).split(",", 1)[1]), np.uint8)
    assert cv2.imdecode(data, cv2.IMREAD_UNCHANGED)[0, 0].tolist() == [0, 0, 255]  # BGR on disk
    grey = np.frombuffer(base64.b64decode(png_data_uri(np.full((2, 2), 0.5)).split(",", 1)[1]), np.uint8)
    assert cv2.imdecode(grey, cv2.IMREAD_UNCHANGED).tolist() == [[128, 128], [128, 128]]


def test_the_report_is_written_atomically(tmp_path):
    path = tmp_path / "asset" / "report.html"
    gate = evaluate_gate(GOOD, GateConfig())
    write_report(path, ReportInputs("stone-42", GOOD, gate, {}, panels()))
    assert path.read_text().startswith("<!DOCTYPE html>")
    assert [p.name for p in path.parent.iterdir()] == ["report.html"]


def test_panels_are_cropped_to_the_stone_with_a_margin():
    mask = torch.zeros(64, 80)
    mask[10:20, 30:50] = 1.0
    view = View("v.png", torch.zeros(64, 80, 3), mask, torch.eye(4), torch.eye(3))
    rows, cols = crop_box(view)
    assert rows.start < 10 and rows.stop > 20 and cols.start < 30 and cols.stop > 50
    assert rows.stop - rows.start < 64 and cols.stop - cols.start < 80
    unmasked = View("v.png", torch.zeros(64, 80, 3), None, torch.eye(4), torch.eye(3))
    assert crop_box(unmasked) == (slice(None), slice(None))
