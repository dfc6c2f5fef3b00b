"""The quality gate: whether an asset ships, and what an operator should do when it does not.

Every check records its value, threshold, pass and a reason written for the operator at 8 a.m.
A metric that is missing fails its check (an unmeasured asset is not a good asset). The verdict
goes to `asset/gate.json` atomically; a failing asset is still written, but quarantined.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from station.scanfolder import atomic_write_json


@dataclass
class GateConfig:
    min_sos: float = 0.9  # Surface Opacity Score: how opaque the surface is seen from every view
    min_psnr: float = 28.0  # dB on held-out views
    min_ssim: float = 0.9  # skimage SSIM, Gaussian window sigma 1.5, on held-out views
    # (mesh volume - infill volume) / mesh volume. The infill sits a margin below the surface: after its
    # erosion is grown back it still misses the surface layer and what depth pruning removed. More than
    # this and the mesh holds far more than its inside, below zero and the inside pokes out through the surface.
    max_volume_mismatch: float = 0.35
    max_infill_excess: float = 0.05
    max_outside_hull_fraction: float = 0.01  # Gaussians outside the masks' visual hull
    require_mesh: bool = True  # watertight + manifold mesh


@dataclass
class GateCheck:
    name: str
    value: Any
    threshold: Any
    passed: bool
    reason: str

    def to_json(self) -> dict:
        return {"name": self.name, "value": self.value, "threshold": self.threshold, "pass": self.passed, "reason": self.reason}


@dataclass
class GateResult:
    passed: bool
    checks: list[GateCheck] = field(default_factory=list)

    def failures(self) -> list[GateCheck]:
        return [c for c in self.checks if not c.passed]

    def summary(self) -> str:
        if self.passed:
            return "gate passed"
        return "gate failed: " + "; ".join(c.reason for c in self.failures())

    def to_json(self) -> dict:
        return {"pass": self.passed, "checks": [c.to_json() for c in self.checks]}


def _number(metrics: dict, key: str) -> float | None:
    value = metrics.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _at_least(name: str, key: str, threshold: float, advice: str) -> Callable[[dict], GateCheck]:
    def check(metrics: dict) -> GateCheck:
        value = _number(metrics, key)
        if value is None:
            return GateCheck(name, metrics.get(key), threshold, False, f"{name}: metric '{key}' missing or not a number; re-run export")
        ok = value >= threshold
        reason = f"{name} {value:.3f} >= {threshold}" if ok else f"{name} {value:.3f} < {threshold}: {advice}"
        return GateCheck(name, value, threshold, ok, reason)

    return check


def _mesh_check(metrics: dict) -> GateCheck:
    watertight, manifold = metrics.get("mesh_watertight"), metrics.get("mesh_manifold")
    value = {"watertight": watertight, "manifold": manifold, "problems": metrics.get("mesh_problems", [])}
    if watertight is None or manifold is None:
        return GateCheck("mesh", value, "watertight and manifold", False, "mesh: no mesh checks recorded; re-run export")
    ok = watertight is True and manifold is True
    if ok:
        return GateCheck("mesh", value, "watertight and manifold", True, "mesh is watertight and manifold")
    problems = "; ".join(value["problems"]) or "watertight/manifold check failed"
    return GateCheck(
        "mesh",
        value,
        "watertight and manifold",
        False,
        f"mesh unusable for printing or volume ({problems}): check the masks and the infill in the report, "
        "then re-run export with a finer voxel size",
    )


def _volume_check(limit: float, excess: float) -> Callable[[dict], GateCheck]:
    def check(metrics: dict) -> GateCheck:
        mesh_v, infill_v = _number(metrics, "mesh_volume_m3"), _number(metrics, "infill_volume_m3")
        if mesh_v is None or infill_v is None or mesh_v <= 0:
            return GateCheck("volume_consistency", None, limit, False, "volume consistency: mesh or infill volume missing; re-run export")
        mismatch = (mesh_v - infill_v) / mesh_v
        ok = -excess <= mismatch <= limit
        if ok:
            reason = f"the infill fills {1 - mismatch:.1%} of the mesh's volume"
        else:
            direction, bound = ("smaller", limit) if mismatch > 0 else ("larger", excess)
            reason = (
                f"infill volume is {abs(mismatch):.1%} {direction} than the mesh's (limit {bound:.0%}): the surface "
                "and the inside disagree; look for a hole or a leak in the report's transmittance maps and retrain"
            )
        return GateCheck("volume_consistency", mismatch, [-excess, limit], ok, reason)

    return check


def _hull_check(limit: float) -> Callable[[dict], GateCheck]:
    def check(metrics: dict) -> GateCheck:
        value = _number(metrics, "outside_hull_fraction")
        if value is None:
            return GateCheck("visual_hull", None, limit, False, "visual hull: fraction of Gaussians outside it not recorded; re-run export")
        ok = value <= limit
        reason = (
            f"{value:.2%} of Gaussians outside the masks' visual hull"
            if ok
            else f"{value:.2%} of Gaussians float outside the masks' visual hull (limit {limit:.1%}): "
            "check the masks for missed background, then retrain"
        )
        return GateCheck("visual_hull", value, limit, ok, reason)

    return check


def evaluate_gate(metrics: dict, config: GateConfig | None = None) -> GateResult:
    """Run every check of `config` against `metrics` (the keys of asset/metrics.json)."""
    config = config or GateConfig()
    checks = [
        _at_least(
            "SOS", "sos", config.min_sos,
            "the surface is see-through; use --method ngs (the default) or a longer preset, and check the "
            "report's transmittance maps for where light leaks",
        ),
        _at_least(
            "PSNR", "psnr", config.min_psnr,
            "held-out views are poorly reproduced; check focus, exposure and the pose report, then retrain longer",
        ),
        _at_least(
            "SSIM", "ssim", config.min_ssim,
            "held-out views lose structure; check for blur or motion in the photos, then retrain longer",
        ),
        _volume_check(config.max_volume_mismatch, config.max_infill_excess),
        _hull_check(config.max_outside_hull_fraction),
    ]
    if config.require_mesh:
        checks.insert(3, _mesh_check)
    results = [check(metrics) for check in checks]
    return GateResult(passed=all(c.passed for c in results), checks=results)


def write_gate(path: Path, result: GateResult) -> None:
    """asset/gate.json, atomically."""
    atomic_write_json(Path(path), result.to_json())
