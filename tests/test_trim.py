"""The shipped splat (station.export.trim): strays below the plate, outside the masks' hull, or tiny and
transparent are left out of the shipped copy, the training model is untouched, and the held-out
PSNR/SOS of both are reported."""

from __future__ import annotations

import numpy as np
import torch

from station.export.splat_model import SplatModel
from station.export.trim import TrimConfig, shipped_splat, trim_masks
from station.ngs.dataset import SceneData, View
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Infill
from station.ngs.sos import evaluate
from station.rig_geometry import look_at_c2w

W, H = 64, 48


def camera(azimuth_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera (OpenCV) of a camera 0.3 m out at 20 degrees elevation, looking at (0, 0, 0.03)."""
    a, e = np.radians(azimuth_deg), np.radians(20.0)
    target = np.array([0.0, 0.0, 0.03])
    eye = target + 0.3 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    viewmat = np.linalg.inv(look_at_c2w(eye, target))
    return torch.tensor(viewmat, dtype=torch.float32), torch.tensor(K, dtype=torch.float32)


def ball(n: int, radius: float, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * radius + [0.0, 0.0, 0.03]


def stone_with_strays() -> tuple[SplatModel, dict[str, slice]]:
    """A grey ball of 400 opaque Gaussians, then 10 below the plate, 10 floating off to the side, 10 faint specks."""
    means = np.concatenate([ball(400, 0.02, 0), ball(10, 0.005, 1) - [0, 0, 0.04], ball(10, 0.005, 2) + [0.08, 0, 0],
                            ball(10, 0.015, 3)])
    n = len(means)
    scales = np.full((n, 3), np.log(0.004))
    scales[430 - 10:] = np.log(0.0002)
    opacity = np.full(n, 4.0)
    opacity[420:] = -6.0
    model = SplatModel(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), opacity, np.zeros((n, 3)), np.zeros((n, 0, 3)))
    return model, {"stone": slice(0, 400), "below_plate": slice(400, 410), "outside_hull": slice(410, 420),
                   "tiny_transparent": slice(420, 430)}


def scene_of(model: SplatModel) -> SceneData:
    """Views of the ball alone, their masks the ball's own render: the hull the strays fall outside."""
    from station.ngs.raster import rasterization

    stone = model.subset(np.arange(400))
    views = []
    for i, azimuth in enumerate(range(0, 360, 45)):
        viewmat, K = camera(azimuth)
        colours, alphas, _ = rasterization(torch.tensor(stone.means), torch.tensor(stone.quats),
                                           torch.tensor(np.exp(stone.scales_log)), torch.tensor(stone.opacity(), dtype=torch.float32),
                                           torch.tensor(stone.rgb()), viewmat[None], K[None], W, H)
        views.append(View(f"v{i}.png", colours[0], (alphas[0, ..., 0] > 0.5).float(), viewmat, K))
    return SceneData(views[1::2], views[0::2], np.zeros((0, 3)), None, 1.0)


def gaussians_of(model: SplatModel) -> Gaussians:
    return Gaussians({"means": torch.tensor(model.means), "scales": torch.tensor(model.scales_log),
                      "quats": torch.tensor(model.quats), "opacities": torch.tensor(model.opacity_logit),
                      "sh0": torch.tensor(model.sh_dc)[:, None], "shN": torch.tensor(model.sh_rest)})


def test_each_kind_of_stray_is_found_and_the_stone_is_kept():
    model, parts = stone_with_strays()
    reasons = trim_masks(model, scene_of(model), 0.01, TrimConfig())
    for reason, mask in reasons.items():
        assert mask[parts[reason]].all(), reason
        assert not mask[parts["stone"]].any(), reason


def test_the_shipped_splat_drops_the_strays_and_reports_the_change_the_model_untouched():
    model, parts = stone_with_strays()
    scene = scene_of(model)
    surface = gaussians_of(model)
    before_params = surface.state_dict()
    infill = Infill(torch.tensor(ball(50, 0.01, 4), dtype=torch.float32), torch.full((50,), 0.004), torch.full((50,), 16))
    before = evaluate(surface, infill, scene.test)
    shipped, block = shipped_splat(model, surface, infill, scene, before, 0.01)
    assert shipped.num == block["shipped_gaussians"] == 400 and block["trained_gaussians"] == 430
    trimmed = block["trimmed"]  # a Gaussian may be trimmed for two reasons: some below the plate are outside the hull too
    assert trimmed["below_plate"] == trimmed["tiny_transparent"] == 10 and 10 <= trimmed["outside_hull"] <= 20
    np.testing.assert_array_equal(shipped.means, model.means[parts["stone"]])
    assert block["psnr_trained"] == before["psnr"] and np.isfinite(block["psnr_shipped"])
    assert block["psnr_change"] == block["psnr_shipped"] - block["psnr_trained"]
    assert block["sos_change"] == block["sos_shipped"] - block["sos_trained"]
    for name, value in surface.state_dict().items():
        torch.testing.assert_close(value, before_params[name])
