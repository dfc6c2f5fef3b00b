"""Geometry errors of a reconstructed mesh against the true one, and the visual-hull check.

Distances are point-to-mesh (samples on one surface to the closest point of the other), not
point-to-point: KD-tree distances between two samplings bottom out at about 0.5*sqrt(area/N),
which at the sample counts we can afford is as large as the errors we want to see.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import binary_dilation
import trimesh

from station.errors import BadInputError


@dataclass
class GeometryErrors:
    accuracy_m: float  # mean distance, prediction samples -> truth surface
    completeness_m: float  # mean distance, truth samples -> prediction surface
    chamfer_l1_m: float  # mean of the two
    precision: float  # fraction of prediction samples within tau of the truth
    recall: float  # fraction of truth samples within tau of the prediction
    fscore: float  # 2PR/(P+R) at tau
    tau_m: float
    bbox_diagonal_m: float  # of the truth
    volume_m3: float
    true_volume_m3: float
    volume_rel_error: float  # (V - V_true) / V_true

    @property
    def chamfer_fraction_of_diagonal(self) -> float:
        return self.chamfer_l1_m / self.bbox_diagonal_m

    def to_json(self) -> dict:
        out = asdict(self)
        out["chamfer_fraction_of_diagonal"] = self.chamfer_fraction_of_diagonal
        return out


def _surface_distance(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    return np.asarray(distance, np.float64)


def compare_meshes(
    predicted: trimesh.Trimesh,
    truth: trimesh.Trimesh,
    samples: int = 10_000,
    tau_fraction: float = 0.01,
    seed: int = 0,
) -> GeometryErrors:
    """Accuracy, completeness, Chamfer-L1, F-score at tau = `tau_fraction` of the truth's bbox
    diagonal, and relative volume error."""
    if len(predicted.faces) == 0 or len(truth.faces) == 0:
        raise BadInputError("compare_meshes: a mesh has no faces")
    rng = np.random.default_rng(seed)
    pred_pts, _ = trimesh.sample.sample_surface(predicted, samples, seed=int(rng.integers(1 << 31)))
    true_pts, _ = trimesh.sample.sample_surface(truth, samples, seed=int(rng.integers(1 << 31)))
    d_pred = _surface_distance(pred_pts, truth)
    d_true = _surface_distance(true_pts, predicted)
    diagonal = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
    tau = tau_fraction * diagonal
    precision = float(np.mean(d_pred < tau))
    recall = float(np.mean(d_true < tau))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    volume, true_volume = float(predicted.volume), float(truth.volume)
    return GeometryErrors(
        accuracy_m=float(d_pred.mean()),
        completeness_m=float(d_true.mean()),
        chamfer_l1_m=float((d_pred.mean() + d_true.mean()) / 2),
        precision=precision,
        recall=recall,
        fscore=fscore,
        tau_m=tau,
        bbox_diagonal_m=diagonal,
        volume_m3=volume,
        true_volume_m3=true_volume,
        volume_rel_error=(volume - true_volume) / true_volume,
    )


def fraction_outside_visual_hull(
    means: np.ndarray, masks: np.ndarray, Ks: np.ndarray, c2ws: np.ndarray, tolerance_px: int = 0
) -> float:
    """Fraction of Gaussian centres that some view sees outside its foreground mask."""
    return float(outside_visual_hull(means, masks, Ks, c2ws, tolerance_px).mean()) if len(means) else 0.0


def outside_visual_hull(
    means: np.ndarray, masks: np.ndarray, Ks: np.ndarray, c2ws: np.ndarray, tolerance_px: int = 0
) -> np.ndarray:
    """[N] bool: the Gaussian centres that some view sees outside its foreground mask.

    means [N, 3]; masks [V, H, W] bool (True = stone); Ks [V, 3, 3]; c2ws [V, 4, 4] OpenCV.
    A centre that projects outside a view's frame or behind its camera is not judged by it.
    `tolerance_px` grows every mask by that many pixels first: surface Gaussians sit on the
    silhouette, and a pixel-quantised mask edge would otherwise reject half of them.
    """
    masks = np.asarray(masks, bool)
    if masks.ndim != 3 or Ks.shape != (len(masks), 3, 3) or c2ws.shape != (len(masks), 4, 4):
        raise BadInputError(f"visual hull: masks {masks.shape}, Ks {Ks.shape}, c2ws {c2ws.shape} disagree")
    if tolerance_px > 0:
        masks = binary_dilation(masks, structure=np.ones((1, 3, 3), bool), iterations=tolerance_px)
    _, height, width = masks.shape
    outside = np.zeros(len(means), bool)
    for mask, K, c2w in zip(masks, Ks, c2ws):
        w2c = np.linalg.inv(c2w)
        cam = means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
        z = cam[:, 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = np.floor(K[0, 0] * cam[:, 0] / zs + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * cam[:, 1] / zs + K[1, 2]).astype(np.int64)
        seen = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        outside[seen] |= ~mask[v[seen], u[seen]]
    return outside
