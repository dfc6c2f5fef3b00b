"""The shipped splat: the trained surface without the Gaussians a viewer should never draw.

Training keeps Gaussians that cost it nothing on the held-out views but spoil an asset seen from
any other angle: centres below the turntable plate (z < 0 in the turntable frame), centres some
view's mask puts outside the object, and Gaussians too small and faint to be seen at all. Only the
shipped copy is trimmed; model/ is never touched, and the held-out PSNR and SOS of both are
reported so a trim that costs quality shows in the metrics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from station.export.geometry_metrics import outside_visual_hull
from station.export.splat_model import SplatModel
from station.ngs.dataset import SceneData
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Infill
from station.ngs.sos import evaluate


@dataclass
class TrimConfig:
    plate_margin_m: float = 0.001  # centres this far below the plate are trimmed
    faint_opacity: float = 0.02  # "transparent": opacity below this ...
    tiny_scale_m: float = 0.0005  # ... and "tiny": largest axis (1 sigma) below this


def trim_masks(model: SplatModel, scene: SceneData, hull_tolerance: float, config: TrimConfig) -> dict[str, np.ndarray]:
    """[N] bool per reason; a Gaussian may have several. `hull_tolerance` is the mask edge allowance
    as a share of the longer image side, as the export's floater check uses it."""
    below = model.means[:, 2] < -config.plate_margin_m
    faint = (model.opacity() < config.faint_opacity) & (np.exp(model.scales_log.max(axis=1)) < config.tiny_scale_m)
    views = [v for v in scene.train + scene.test if v.mask is not None]
    outside = np.zeros(model.num, bool)
    if views:
        masks = np.stack([v.mask.numpy() > 0.5 for v in views])  # [V, H, W]
        Ks = np.stack([v.K.double().numpy() for v in views])
        c2ws = np.linalg.inv(np.stack([v.viewmat.double().numpy() for v in views]))
        tolerance = max(2, round(hull_tolerance * max(masks.shape[1:])))
        outside = outside_visual_hull(model.means.astype(np.float64), masks, Ks, c2ws, tolerance)
    return {"below_plate": below, "outside_hull": outside, "tiny_transparent": faint}


def shipped_splat(model: SplatModel, surface: Gaussians, infill: Infill, scene: SceneData, before: dict,
                  hull_tolerance: float, config: TrimConfig | None = None) -> tuple[SplatModel, dict]:
    """(the trimmed model, its metrics block): counts by reason and the held-out PSNR/SOS change.

    `model` is `surface` as a SplatModel; `before` is `evaluate` of `surface` on scene.test, which the
    export has already run."""
    reasons = trim_masks(model, scene, hull_tolerance, config or TrimConfig())
    drop = np.logical_or.reduce(list(reasons.values()))
    kept_all = bool(drop.all())  # nothing would be left to ship: the trained splat ships instead
    drop &= not kept_all
    keep = torch.from_numpy(~drop)
    shipped = Gaussians({name: value.detach()[keep] for name, value in surface.params.items()})
    after = evaluate(shipped, infill, scene.test)
    block = {
        "trained_gaussians": model.num,
        "shipped_gaussians": int((~drop).sum()),
        "trimmed": {reason: int(mask.sum()) for reason, mask in reasons.items()},
        "psnr_trained": before["psnr"],
        "psnr_shipped": after["psnr"],
        "psnr_change": after["psnr"] - before["psnr"],
        "sos_trained": before["sos"],
        "sos_shipped": after["sos"],
        "sos_change": after["sos"] - before["sos"],
        "kept_all_because_trim_left_nothing": kept_all,
    }
    return model.subset(np.flatnonzero(~drop)), block
