"""Does a scan still match its rig model? Each elevation ring is refitted, as one body, to the feature matches.

A slipped tilt arm or a wobbling plate moves a whole ring of cameras the same way as seen from each
camera. So each ring gets one offset (a turn and a shift, in its cameras' frame) that best explains its
verified matches, by their epipolar (Sampson) distance, with every other ring held where the rig puts it.
A weak prior holds the offset at zero, so it moves only as far as the matches ask. The ring drifted when
that offset is large enough to matter and the matches sit clearly closer to their epipolar lines after the
refit than at the rig's poses. On a small stone a ring can orbit it by half a degree and barely move its
matches off their epipolar lines: there the images cannot tell, and neither does the check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from station.process.sfm import VerifiedMatches

# The offset is held at zero with the weight of this many matches, each one pixel off per pixel the offset
# moves the image: the matches move it only where they can see, so a direction they cannot see stays at zero
# instead of wandering with the noise.
PRIOR_MATCHES = 100.0
LOSS_SCALE_PX = 1.0  # Cauchy scale: a mismatch that survived verification weighs little


@dataclass(frozen=True)
class DriftLimits:
    rotation_deg: float = 0.5  # a ring's turn against the rig, in its cameras' frame, that needs recalibrating
    centre_fraction: float = 0.01  # a ring's shift against the rig, of the orbit radius, that needs recalibrating
    min_gain: float = 1.5  # the refit must bring the ring's median epipolar distance down by this factor
    min_matches: int = 100  # matches to other rings a ring needs for a verdict


@dataclass(frozen=True)
class RingFit:
    matches: int  # verified matches between this ring and the others
    epipolar_px_rig: float  # median epipolar distance of the ring's matches at the rig's poses (drifted rings moved)
    epipolar_px_refit: float  # the same after the ring's refit
    turn_deg: tuple[float, float, float]  # the refit's rotation vector, in the ring's camera frame
    shift_fraction: tuple[float, float, float]  # the refit's centre shift, in the camera frame, of the orbit radius
    explained: float  # how much of the robust cost of all the ring's matches the refit removes

    @property
    def rotation_deg(self) -> float:
        return float(np.linalg.norm(self.turn_deg))

    @property
    def centre_fraction(self) -> float:
        return float(np.linalg.norm(self.shift_fraction))

    @property
    def gain(self) -> float:
        return self.epipolar_px_rig / max(self.epipolar_px_refit, 1e-12)


def epipolar_px(matches: VerifiedMatches, rotations: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Signed Sampson distance of each match, in pixels, for world-to-camera `rotations` [V, 3, 3] and camera
    `centres` [V, 3] of the views `matches.names`.

    Not pycolmap's compute_squared_sampson_error: that takes one pair at a time and loses the sign, and
    least_squares needs every pair's residuals, signed, at each of its evaluations."""
    first, second = matches.pairs[:, 0], matches.pairs[:, 1]
    relative = rotations[second] @ np.transpose(rotations[first], (0, 2, 1))  # first camera to second
    t = np.einsum("pij,pj->pi", rotations[second], centres[first] - centres[second])
    skew = np.zeros_like(relative)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    e = (skew @ relative)[matches.pair_of]  # the essential matrix of each match's pair
    (xa, ya), (xb, yb) = matches.points[:, 0].T, matches.points[:, 1].T
    line_b = [e[:, i, 0] * xa + e[:, i, 1] * ya + e[:, i, 2] for i in range(3)]  # E x_a
    line_a = [e[:, 0, i] * xb + e[:, 1, i] * yb + e[:, 2, i] for i in range(2)]  # (E^T x_b)[:2]
    constraint = xb * line_b[0] + yb * line_b[1] + line_b[2]
    norm = np.sqrt(line_b[0] ** 2 + line_b[1] ** 2 + line_a[0] ** 2 + line_a[1] ** 2)
    return matches.focal_px * constraint / np.maximum(norm, 1e-12)


def pairs_kept(matches: VerifiedMatches, keep: np.ndarray) -> VerifiedMatches:
    """The matches of the pairs `keep` (bool [P]), the pairs renumbered."""
    renumber = np.cumsum(keep) - 1
    in_kept = keep[matches.pair_of]
    return VerifiedMatches(matches.names, matches.pairs[keep], renumber[matches.pair_of[in_kept]],
                           matches.points[in_kept], matches.focal_px)


def _cauchy_cost(residuals: np.ndarray) -> float:
    """scipy's least_squares cost of `residuals` under its Cauchy loss at LOSS_SCALE_PX."""
    return float(0.5 * LOSS_SCALE_PX**2 * np.log1p((residuals / LOSS_SCALE_PX) ** 2).sum())


def _moved(rotations: np.ndarray, centres: np.ndarray, in_ring: np.ndarray,
           offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera rotations and centres with the views `in_ring` turned by offset[:3] (a rotation vector)
    and shifted by offset[3:], both in each camera's own frame."""
    turned, shifted = rotations.copy(), centres.copy()
    turned[in_ring] = Rotation.from_rotvec(offset[:3]).as_matrix().T @ rotations[in_ring]
    shifted[in_ring] = centres[in_ring] + np.einsum("nji,j->ni", rotations[in_ring], offset[3:])
    return turned, shifted


def refit_ring(matches: VerifiedMatches, rotations: np.ndarray, centres: np.ndarray, in_ring: np.ndarray,
               radius: float) -> tuple[RingFit, np.ndarray]:
    """The one offset (turn, shift) of the views `in_ring` (bool [V]) that best explains their matches, every
    other view held at its world-to-camera rotation and centre; the fit and the offset."""
    ring_matches = pairs_kept(matches, in_ring[matches.pairs].any(axis=1))
    if len(ring_matches.pair_of) == 0:
        return RingFit(0, 0.0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0), np.zeros(6)
    prior = np.sqrt(PRIOR_MATCHES) * matches.focal_px

    def residuals(offset: np.ndarray) -> np.ndarray:
        return np.concatenate([epipolar_px(ring_matches, *_moved(rotations, centres, in_ring, offset)),
                               prior * np.concatenate([offset[:3], offset[3:] / radius])])

    start = epipolar_px(ring_matches, rotations, centres)
    fit = least_squares(residuals, np.zeros(6), loss="cauchy", f_scale=LOSS_SCALE_PX,
                        x_scale=np.concatenate([np.full(3, 1e-2), np.full(3, 1e-2 * radius)]))
    crossing = in_ring[ring_matches.pairs].sum(axis=1) == 1
    ring_fit = RingFit(int(crossing[ring_matches.pair_of].sum()), float(np.median(np.abs(start))),
                       float(np.median(np.abs(fit.fun[:-6]))), tuple(float(v) for v in np.degrees(fit.x[:3])),
                       tuple(float(v) for v in fit.x[3:] / radius), _cauchy_cost(start) - float(fit.cost))
    return ring_fit, fit.x


def _offset_text(elevation: float, fit: RingFit) -> str:
    return (f"{elevation}: {fit.rotation_deg:.2f} deg, {100 * fit.centre_fraction:.2f} % (matches "
            f"{fit.epipolar_px_rig:.2f} px off their epipolar lines, {fit.epipolar_px_refit:.2f} px refitted)")


def check_rig(matches: VerifiedMatches, rig_poses: dict[str, np.ndarray], elevation_of: dict[str, float],
              radius: float, limits: DriftLimits) -> dict:
    """The cross-check's report: each ring's refit, the drifted elevations and the operator's flags. Every view
    of `matches` must have a rig pose and an elevation.

    A ring that moved drags its neighbours' refits along through the matches they share: a neighbour moved
    towards it fits their shared matches too. So the rings are judged one at a time: the drifted ring whose
    refit explains most of the matches is moved by its offset before the others are refitted.
    """
    rotations = np.array([rig_poses[n][:3, :3].T for n in matches.names])
    centres = np.array([rig_poses[n][:3, 3] for n in matches.names])
    elevations = np.array([elevation_of[n] for n in matches.names])
    out: dict = {"matches": len(matches.pair_of), "ring_offsets": {}, "flags": []}
    unmatched = sorted(set(matches.names) - {matches.names[v] for v in np.unique(matches.pairs)})
    if unmatched:
        out["flags"].append(f"cross-check: no verified matches in {len(unmatched)} of {len(matches.names)} views: "
                            f"{', '.join(unmatched)}")

    def drifts(fit: RingFit) -> bool:
        return (fit.matches >= limits.min_matches and fit.gain >= limits.min_gain
                and (fit.rotation_deg > limits.rotation_deg or fit.centre_fraction > limits.centre_fraction))

    fits, drifted, pending = {}, [], sorted(set(elevations.tolist()))
    while pending:
        fits.update({e: refit_ring(matches, rotations, centres, elevations == e, radius) for e in pending})
        found = [e for e in pending if drifts(fits[e][0])]
        if not found:
            break
        worst = max(found, key=lambda e: fits[e][0].explained)
        drifted.append(worst)
        pending.remove(worst)
        rotations, centres = _moved(rotations, centres, elevations == worst, fits[worst][1])
    for e, (fit, _) in sorted(fits.items()):
        out["ring_offsets"][str(e)] = {"matches": fit.matches, "epipolar_px_rig": fit.epipolar_px_rig,
                                       "epipolar_px_refit": fit.epipolar_px_refit, "turn_deg": fit.turn_deg,
                                       "shift_fraction": fit.shift_fraction, "rotation_deg": fit.rotation_deg,
                                       "centre_fraction": fit.centre_fraction}
    drifted.sort()
    out["drifted_elevations"] = drifted
    unjudged = [e for e, (fit, _) in sorted(fits.items()) if fit.matches < limits.min_matches]
    if unjudged:
        out["flags"].append(f"cross-check inconclusive for elevations {unjudged}: fewer than {limits.min_matches} "
                            "matches to the other rings; their poses rest on the rig model alone")
    if drifted:
        offsets = ", ".join(_offset_text(e, fits[e][0]) for e in drifted)
        out["flags"].append(f"elevations {drifted} disagree with the rig model (drift; ring turn and shift of the "
                            f"orbit radius: {offsets}): recalibrate the rig")
    return out
