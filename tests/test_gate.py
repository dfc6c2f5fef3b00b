"""The quality gate: a good asset passes; a see-through model, a broken mesh, floaters and
missing metrics each fail their own check with a reason an operator can act on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from station.export.gate import GateConfig, evaluate_gate, write_gate
from station.export.mesh import check_mesh

pytestmark = pytest.mark.no_kernels


def good_metrics() -> dict:
    return {
        "sos": 0.97,
        "psnr": 31.2,
        "ssim": 0.95,
        "mesh_watertight": True,
        "mesh_manifold": True,
        "mesh_problems": [],
        "mesh_volume_m3": 2.0e-4,
        "infill_volume_m3": 1.9e-4,
        "outside_hull_fraction": 0.001,
    }


def failed(result) -> dict[str, str]:
    return {c.name: c.reason for c in result.checks if not c.passed}


def test_good_asset_passes_every_check():
    result = evaluate_gate(good_metrics())
    assert result.passed, result.summary()
    assert [c.name for c in result.checks] == ["SOS", "PSNR", "SSIM", "mesh", "volume_consistency", "visual_hull"]


def test_transparent_model_fails_on_sos_and_volume_with_advice():
    # What a plain 3DGS baseline looks like: sharp photos, see-through surface, almost no inside.
    metrics = good_metrics() | {"sos": 0.41, "infill_volume_m3": 0.6e-4}
    result = evaluate_gate(metrics)
    assert not result.passed
    reasons = failed(result)
    assert set(reasons) == {"SOS", "volume_consistency"}
    assert "0.410 < 0.9" in reasons["SOS"] and "see-through" in reasons["SOS"] and "--method ngs" in reasons["SOS"]
    assert "70.0% smaller" in reasons["volume_consistency"]


def test_an_infill_a_margin_below_the_surface_is_consistent_but_one_poking_out_is_not():
    below = evaluate_gate(good_metrics() | {"mesh_volume_m3": 1.5e-4, "infill_volume_m3": 1.17e-4})
    assert below.passed
    reasons = failed(evaluate_gate(good_metrics() | {"mesh_volume_m3": 1.5e-4, "infill_volume_m3": 1.65e-4}))
    assert set(reasons) == {"volume_consistency"} and "10.0% larger" in reasons["volume_consistency"]


def test_broken_mesh_fails_the_mesh_check_with_its_problems():
    box = trimesh.creation.box()
    box.update_faces([True] * (len(box.faces) - 1) + [False])
    metrics = good_metrics() | check_mesh(box).to_metrics()
    reasons = failed(evaluate_gate(metrics))
    assert "mesh" in reasons  # (the open box's volume also disagrees with the infill's)
    assert "not watertight" in reasons["mesh"] and "re-run export" in reasons["mesh"]


def test_floaters_outside_the_visual_hull_fail_and_point_at_the_masks():
    reasons = failed(evaluate_gate(good_metrics() | {"outside_hull_fraction": 0.08}))
    assert list(reasons) == ["visual_hull"]
    assert "8.00%" in reasons["visual_hull"] and "masks" in reasons["visual_hull"]


def test_missing_or_non_finite_metrics_fail_rather_than_pass():
    metrics = good_metrics()
    del metrics["psnr"]
    metrics["ssim"] = float("nan")
    reasons = failed(evaluate_gate(metrics))
    assert set(reasons) == {"PSNR", "SSIM"}
    assert "missing" in reasons["PSNR"]


def test_thresholds_come_from_the_config():
    metrics = good_metrics() | {"psnr": 26.0}
    assert not evaluate_gate(metrics).passed
    assert evaluate_gate(metrics, GateConfig(min_psnr=25.0)).passed


def test_gate_json_has_pass_and_checks_with_value_threshold_pass(tmp_path: Path):
    path = tmp_path / "asset" / "gate.json"
    write_gate(path, evaluate_gate(good_metrics() | {"sos": 0.5}))
    data = json.loads(path.read_text())
    assert data["pass"] is False
    sos = next(c for c in data["checks"] if c["name"] == "SOS")
    assert sos == {"name": "SOS", "value": 0.5, "threshold": 0.9, "pass": False, "reason": sos["reason"]}
    assert [p.name for p in path.parent.iterdir()] == ["gate.json"]  # no temp file left behind
