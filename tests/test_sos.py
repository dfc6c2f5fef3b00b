"""SOS and the starred metrics: opaque surfaces score 1, leaky ones less, and nothing crashes."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from station.errors import BadInputError
from station.ngs.dataset import View
from station.ngs.conventions import rgb_to_sh
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Infill, InfillConfig, build_infill
from station.ngs.inria_ply import read_inria_ply
from station.ngs.raster import rasterization
from station.ngs.sos import evaluate, held_out_sos, scan_infill, sos_of_transmittance
from station.scanfolder import ScanFolder
from test_ngs_infill import ring_cameras, sphere_surface

TINY = InfillConfig(levels=(8, 16), erosion_iters=(2, 2), prune_downscale=1)


def sphere_model(opacity: float) -> Gaussians:
    s = sphere_surface()
    n = len(s["means"])
    return Gaussians({
        "means": s["means"], "quats": s["quats"], "scales": s["scales"].log(),
        "opacities": torch.full((n,), math.log(opacity / (1 - opacity))),
        "sh0": rgb_to_sh(torch.tensor([0.6, 0.5, 0.4])).expand(n, 1, 3).clone(), "shN": torch.zeros(n, 3, 3),
    })


@pytest.fixture(scope="module")
def scene() -> tuple[list[View], Infill]:
    """Held-out views of the opaque sphere (its own renders as ground truth) and its infill."""
    opaque = sphere_model(0.99)
    g = {k: v.detach() for k, v in opaque.activated().items()}
    views = []
    for k, cam in enumerate(ring_cameras()[::3]):
        with torch.no_grad():
            rgb, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                          cam.viewmat[None], cam.K[None], cam.width, cam.height, sh_degree=1)
        views.append(View(f"v{k}.png", rgb[0].clamp(0, 1), (alpha[0, ..., 0] > 0.5).float(), cam.viewmat, cam.K))
    return views, build_infill(g, ring_cameras(), TINY)


def test_sos_matches_the_reference_points():
    for t, expected in ((0.1, 0.1), (1e-3, 0.3), (1e-5, 0.5), (0.0, 1.0)):
        assert sos_of_transmittance(t) == pytest.approx(expected, abs=1e-6)


def test_an_opaque_sphere_with_infill_scores_one_and_its_renders_match(scene, tmp_path):
    views, infill = scene
    result = evaluate(sphere_model(0.99), infill, views, tmp_path)
    assert result["sos"] > 0.99
    assert result["psnr"] > 40 and result["psnr_star"] > 40
    assert result["num_infill"] == len(infill) > 0
    assert result["lpips"] == "skipped"
    maps = sorted(tmp_path.glob("*_transmittance.png"))
    assert len(maps) == len(views)
    assert cv2.imread(str(maps[0]), cv2.IMREAD_UNCHANGED).dtype == np.uint16


def test_sos_falls_as_the_surface_opacity_drops(scene):
    views, infill = scene
    scores = [evaluate(sphere_model(a), infill, views)["sos"] for a in (0.99, 0.8, 0.5, 0.2)]
    assert all(a > b for a, b in zip(scores, scores[1:])), scores
    assert scores[-1] < 0.3


def test_training_scores_the_same_sos_as_export_and_the_worst_views_leak_in_pixels_of_green(scene):
    views, infill = scene
    for opacity in (0.99, 0.3):
        model = sphere_model(opacity)
        sos, leak_px = held_out_sos({k: v.detach() for k, v in model.activated().items()}, infill, views)
        exported = evaluate(model, infill, views)
        assert sos == pytest.approx(exported["sos"], abs=1e-9)
        # a view's summed green is its transmittance times its mask's area; the leak is the largest of them
        green = [row["transmittance"] * float(v.mask.sum()) for row, v in zip(exported["views"], views)]
        assert leak_px == pytest.approx(max(green), rel=1e-5, abs=1e-9)
        assert (leak_px < 1 / 510) == (opacity == 0.99)  # an opaque sphere shows nothing; a 30% one shows its core
    nothing_to_hide = infill.select(torch.zeros(len(infill), dtype=torch.bool))
    assert held_out_sos({}, nothing_to_hide, views) == (None, None)


def test_leaking_infill_lowers_psnr_star_below_psnr(scene):
    views, infill = scene
    leaky = evaluate(sphere_model(0.3), infill, views)
    opaque = evaluate(sphere_model(0.99), infill, views)
    assert leaky["psnr_star"] < leaky["psnr"]
    assert opaque["psnr_star"] == pytest.approx(opaque["psnr"], abs=1e-6)


def test_views_without_masks_fall_back_to_the_rendered_alpha(scene):
    views, infill = scene
    unmasked = [View(v.name, v.image, None, v.viewmat, v.K) for v in views]
    result = evaluate(sphere_model(0.99), infill, unmasked)
    assert result["sos"] > 0.99
    assert {row["mask_source"] for row in result["views"]} == {"rendered alpha"}


def test_an_empty_infill_cannot_be_scored_instead_of_scoring_a_perfect_one(scene):
    views, infill = scene
    with pytest.raises(BadInputError, match="infill .* empty"):
        evaluate(sphere_model(0.2), infill.select(torch.zeros(len(infill), dtype=torch.bool)), views)


def test_a_scan_whose_trained_infill_is_empty_is_scored_with_one_built_from_its_surface(scene, tmp_path):
    views, infill = scene
    (tmp_path / "model").mkdir()
    torch.save(infill.select(torch.zeros(len(infill), dtype=torch.bool)).state_dict(), tmp_path / "model" / "infill.pt")
    built, source = scan_infill(ScanFolder(tmp_path), sphere_model(0.99), ring_cameras())
    assert len(built) > 0 and source == "built from the scored splat (the trained infill is empty)"


def write_inria_ply(path, model: Gaussians) -> None:
    p = {k: v.detach().numpy() for k, v in model.params.items()}
    n, rest = len(model), p["shN"].shape[1] * 3
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    columns = [p["means"], np.zeros((n, 3)), p["sh0"][:, 0], p["shN"].transpose(0, 2, 1).reshape(n, -1),
               p["opacities"][:, None], p["scales"], p["quats"]]
    data = np.concatenate(columns, axis=1).astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path.write_bytes(header.encode() + data.tobytes())


def test_inria_ply_round_trips_every_parameter(tmp_path):
    model = sphere_model(0.7)
    model.params["shN"].data = torch.randn_like(model.params["shN"])
    write_inria_ply(tmp_path / "s.ply", model)
    back = read_inria_ply(tmp_path / "s.ply")
    for name, value in model.params.items():
        torch.testing.assert_close(back.params[name], value.detach())


def test_truncated_and_garbage_plys_are_refused_with_the_file_named(tmp_path):
    write_inria_ply(tmp_path / "s.ply", sphere_model(0.7))
    data = (tmp_path / "s.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-100])
    (tmp_path / "junk.ply").write_bytes(b"\x00garbage" * 10)
    with pytest.raises(BadInputError, match="cut.ply: truncated"):
        read_inria_ply(tmp_path / "cut.ply")
    with pytest.raises(BadInputError, match="junk.ply: not a PLY"):
        read_inria_ply(tmp_path / "junk.ply")


def test_a_coverage_mask_scores_a_render_of_the_object_alone_on_black_as_exact(scene):
    # process writes masks as coverage and, on the edge pixels, the object's own colour (straight alpha);
    # the metrics compare the render with image x coverage, so a perfect model loses nothing at the rim
    views, infill = scene
    model = sphere_model(0.99)
    g = {k: v.detach() for k, v in model.activated().items()}
    plate = torch.tensor([0.8, 0.8, 0.8])
    straight, shot_like = [], []
    for view in views:
        with torch.no_grad():
            rgb, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                          view.viewmat[None], view.K[None], view.width, view.height, sh_degree=1)
        coverage = alpha[0, ..., 0]
        assert bool(((coverage > 0.05) & (coverage < 0.95)).any())  # the sphere has a soft rim to score
        colour = torch.where(coverage[..., None] > 1e-4, rgb[0] / coverage.clamp_min(1e-4)[..., None], 0.0)
        straight.append(View(view.name, colour.clamp(0, 1), coverage, view.viewmat, view.K))
        photo = (rgb[0] + (1 - coverage[..., None]) * plate).clamp(0, 1)  # the rim mixed with the plate
        shot_like.append(View(view.name, photo, (coverage > 0.5).float(), view.viewmat, view.K))
    assert evaluate(model, infill, straight)["psnr"] > 40
    assert evaluate(model, infill, shot_like)["psnr"] < evaluate(model, infill, straight)["psnr"] - 5
