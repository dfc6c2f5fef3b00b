"""The drift cross-check: a ring of cameras that moved against the rig model is found from the feature matches,
and one the images cannot tell apart from the model is not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from station.process.drift import DriftLimits, check_rig, epipolar_px, pairs_kept
from station.process.rig_model import RigModel, axis_rotation
from station.process.sfm import VerifiedMatches
from station.rig_geometry import RigGeometry

RIG = RigGeometry().scaled(320, 240)
ELEVATIONS = (15.0, 40.0, 65.0)
MODEL = RigModel.nominal(RIG, list(ELEVATIONS))
NAMES = [f"e{i}_a{j:03d}.png" for i in range(len(ELEVATIONS)) for j in range(20)]
ELEVATION_OF = {n: ELEVATIONS[int(n[1])] for n in NAMES}
RIG_POSES = {n: MODEL.camera_to_world(ELEVATION_OF[n], 18.0 * int(n[4:7])) for n in NAMES}
CENTRE = MODEL.axis_point


def matches_seen_from(true_poses: dict[str, np.ndarray], stone_radius: float, noise_px: float = 0.2,
                      max_angle_deg: float = 50.0, seed: int = 0) -> VerifiedMatches:
    """Matches of points on a stone of `stone_radius` (metres) at the turntable centre, as cameras at
    `true_poses` see them, between views less than `max_angle_deg` apart, with `noise_px` of pixel noise."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(400, 3))
    points = CENTRE + stone_radius * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    focal = float(RIG.intrinsics()[0, 0])
    looks = {n: p[:3, 2] for n, p in true_poses.items()}

    def seen(name: str) -> np.ndarray:
        c2w = true_poses[name]
        cam = (points - c2w[:3, 3]) @ c2w[:3, :3]
        return cam[:, :2] / cam[:, 2:] + rng.normal(scale=noise_px / focal, size=(len(points), 2))

    observed = {n: seen(n) for n in NAMES}
    facing = {n: (points - CENTRE) @ -looks[n] > 0 for n in NAMES}  # the stone's side this camera sees
    pairs, pair_of, matched = [], [], []
    for a in range(len(NAMES)):
        for b in range(a + 1, len(NAMES)):
            na, nb = NAMES[a], NAMES[b]
            if np.degrees(np.arccos(np.clip(looks[na] @ looks[nb], -1, 1))) > max_angle_deg:
                continue
            both = facing[na] & facing[nb]
            pair_of.append(np.full(both.sum(), len(pairs)))
            pairs.append((a, b))
            matched.append(np.stack([observed[na][both], observed[nb][both]], axis=1))
    return VerifiedMatches(NAMES, np.array(pairs), np.concatenate(pair_of), np.concatenate(matched), focal)


def ring_moved(ring: float, move) -> dict[str, np.ndarray]:
    return {n: move(p) if ELEVATION_OF[n] == ring else p for n, p in RIG_POSES.items()}


def turned_in_place(degrees: float):
    """Each camera turned about its own x axis (a loose camera mount)."""
    def move(c2w: np.ndarray) -> np.ndarray:
        out = c2w.copy()
        out[:3, :3] = c2w[:3, :3] @ Rotation.from_rotvec([np.radians(degrees), 0.0, 0.0]).as_matrix()
        return out
    return move


def orbited(degrees: float):
    """Each camera carried round the turntable centre, still looking at it (a slipped tilt arm)."""
    return lambda c2w: axis_rotation(CENTRE, c2w[:3, 0], degrees) @ c2w


def check(matches: VerifiedMatches) -> dict:
    return check_rig(matches, RIG_POSES, ELEVATION_OF, MODEL.orbit_radius(), DriftLimits())


def test_the_epipolar_distance_of_exact_matches_is_zero_and_grows_with_a_wrong_pose():
    matches = matches_seen_from(RIG_POSES, 0.045, noise_px=0.0)
    rotations = np.array([RIG_POSES[n][:3, :3].T for n in NAMES])
    centres = np.array([RIG_POSES[n][:3, 3] for n in NAMES])
    assert np.abs(epipolar_px(matches, rotations, centres)).max() < 1e-9
    wrong = rotations.copy()
    wrong[0] = Rotation.from_rotvec([0.0, 0.01, 0.0]).as_matrix() @ wrong[0]
    assert np.median(np.abs(epipolar_px(matches, wrong, centres)[matches.pairs[matches.pair_of, 0] == 0])) > 1.0


def test_a_rig_that_matches_the_images_is_no_drift_and_no_ring_moves():
    result = check(matches_seen_from(RIG_POSES, 0.045))
    assert result["drifted_elevations"] == [] and result["flags"] == []
    for ring in result["ring_offsets"].values():
        assert ring["rotation_deg"] < 0.05 and ring["centre_fraction"] < 0.001
        assert ring["epipolar_px_refit"] == pytest.approx(ring["epipolar_px_rig"], rel=0.05)


@pytest.mark.parametrize("move, size", [(turned_in_place(1.0), "rotation_deg"), (orbited(3.0), "centre_fraction")])
def test_a_ring_that_moved_as_one_is_drift_and_only_that_ring(move, size):
    result = check(matches_seen_from(ring_moved(40.0, move), 0.045))
    assert result["drifted_elevations"] == [40.0]
    moved = result["ring_offsets"]["40.0"]
    assert moved["epipolar_px_rig"] > 3 * moved["epipolar_px_refit"]
    assert moved[size] > {"rotation_deg": 0.5, "centre_fraction": 0.01}[size]
    assert any("elevations [40.0] disagree with the rig model" in f and "recalibrate the rig" in f
               for f in result["flags"])


def test_a_turn_in_place_is_measured_at_its_size():
    result = check(matches_seen_from(ring_moved(65.0, turned_in_place(2.0)), 0.045))
    assert result["ring_offsets"]["65.0"]["rotation_deg"] == pytest.approx(2.0, abs=0.1)


def test_on_a_stone_small_in_frame_an_orbit_the_images_cannot_see_is_no_drift_but_a_turn_they_can_is():
    # a 1 cm stone at 0.45 m: orbiting it by half a degree moves no match a tenth of a pixel off its epipolar line
    unseen = check(matches_seen_from(ring_moved(40.0, orbited(0.5)), 0.01))
    assert unseen["drifted_elevations"] == []
    seen = check(matches_seen_from(ring_moved(40.0, turned_in_place(0.8)), 0.01))
    assert seen["drifted_elevations"] == [40.0]


def test_a_ring_with_too_few_matches_to_the_others_gets_no_verdict():
    matches = matches_seen_from(ring_moved(65.0, turned_in_place(2.0)), 0.045)
    high = np.array([ELEVATION_OF[n] == 65.0 for n in NAMES])
    crossing = high[matches.pairs].sum(axis=1) == 1
    keep = ~crossing[matches.pair_of]
    keep[np.flatnonzero(crossing[matches.pair_of])[:50]] = True  # 50 matches to the other rings are left
    thinned = VerifiedMatches(NAMES, matches.pairs, matches.pair_of[keep], matches.points[keep], matches.focal_px)
    result = check(thinned)
    assert 65.0 not in result["drifted_elevations"]
    assert any("cross-check inconclusive for elevations [65.0]" in f for f in result["flags"])


def test_a_view_without_matches_is_named():
    matches = matches_seen_from(RIG_POSES, 0.045)
    lost = NAMES.index("e1_a003.png")
    result = check(pairs_kept(matches, ~(matches.pairs == lost).any(axis=1)))
    assert any("no verified matches in 1 of 60 views: e1_a003.png" in f for f in result["flags"])
    assert result["drifted_elevations"] == []
