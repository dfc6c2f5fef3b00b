"""The surface Gaussians as raw, unconstrained parameters (gsplat's `splats` layout).

Parameters are stored the way the optimiser wants them (log-scales, opacity logits, SH
coefficients) and activated only when rendering, so Adam never steps out of the valid range.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from station.errors import BadInputError
from station.ngs.conventions import rgb_to_sh

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


class Gaussians:
    """A dict of leaf parameters: means [N,3], scales [N,3] (log), quats [N,4] wxyz,
    opacities [N] (logit), sh0 [N,1,3], shN [N,K-1,3]."""

    def __init__(self, params: dict[str, torch.Tensor]):
        missing = [name for name in PARAM_NAMES if name not in params]
        if missing:
            raise BadInputError(f"Gaussian parameters lack {missing}")
        self.params: dict[str, torch.nn.Parameter] = {
            name: torch.nn.Parameter(params[name].detach().clone().float()) for name in PARAM_NAMES
        }

    @staticmethod
    def from_points(points: np.ndarray, colors: np.ndarray | None, sh_degree: int, seed: int = 0,
                    device: torch.device | str = "cpu") -> "Gaussians":
        """3DGS initialisation: opacity 0.1, scale = mean distance to the 3 nearest neighbours."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
            raise BadInputError(f"initial cloud must be [N>=4, 3] points, got shape {points.shape}")
        dist, _ = cKDTree(points).query(points, k=4)  # [N, 4], first column is the point itself
        mean_dist = np.clip(dist[:, 1:].mean(axis=1), 1e-7, None)
        n = len(points)
        if colors is None:
            generator = np.random.default_rng(seed)
            colors = generator.random((n, 3))
        rgb = torch.as_tensor(np.asarray(colors, dtype=np.float32), device=device)  # [N, 3] in [0, 1]
        quats = torch.zeros(n, 4, device=device)
        quats[:, 0] = 1.0
        params = {
            "means": torch.as_tensor(points, dtype=torch.float32, device=device),
            "scales": torch.log(torch.as_tensor(mean_dist, dtype=torch.float32, device=device))[:, None].repeat(1, 3),
            "quats": quats,
            "opacities": torch.full((n,), math.log(0.1 / 0.9), device=device),
            "sh0": rgb_to_sh(rgb)[:, None, :],
            "shN": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=device),
        }
        return Gaussians(params)

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.params["shN"].shape[1] + 1))) - 1

    def activated(self) -> dict[str, torch.Tensor]:
        """What the rasteriser takes: linear scales, unit quats, opacities in [0,1], SH [N,K,3]."""
        p = self.params
        return {
            "means": p["means"],  # [N, 3]
            "quats": torch.nn.functional.normalize(p["quats"], dim=-1),  # [N, 4]
            "scales": torch.exp(p["scales"]),  # [N, 3]
            "opacities": torch.sigmoid(p["opacities"]),  # [N]
            "colors": torch.cat([p["sh0"], p["shN"]], dim=1),  # [N, K, 3]
        }

    def to(self, device: torch.device | str) -> "Gaussians":
        """The same parameters as new leaves on `device` (the trainer's device option)."""
        return Gaussians({name: value.detach().to(device) for name, value in self.params.items()})

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {name: value.detach().clone() for name, value in self.params.items()}

    @staticmethod
    def from_state_dict(state: dict[str, torch.Tensor]) -> "Gaussians":
        return Gaussians(state)
