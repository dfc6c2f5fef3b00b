"""The trainer, its strategies and its scan-folder I/O, on a tiny sphere scene (32x32 views)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import numba
import torch

from station.errors import BadInputError, TrainingError
from station.ngs.dataset import OPENGL_TO_OPENCV, downscaled_view, load_scene
from station.ngs import _kernels, _project_kernels, _ssim_kernels
from station.ngs.conventions import ALPHA_MIN, rgb_to_sh
from station.ngs.infill import InfillConfig
from station.ngs.losses import LossConfig, alpha_losses, mask_regions, total_loss
from station.ngs.ngs_schedule import NGSConfig
from station.ngs.pipeline import write_model
from station.ngs.raster import rasterization
from station.ngs.resolution import ResolutionConfig, resolution_decision
from station.ngs.presets import make_config
from station.ngs.sos import evaluate_scan, score_splat
from station.ngs.sh_degree import cut_to_degree, sh_degree_choice
from station.ngs.stopping import ExtendConfig, early_finish_decision, extension_decision
from station.ngs.strategy import DefaultStrategy, DensifyConfig
from station.ngs.trainer import TrainConfig, Trainer
from station.ngs.warmup import exercise_kernels, start_kernel_warmup
from test_ngs_infill import ring_cameras, sphere_surface
from test_sos import write_inria_ply

TINY = TrainConfig(
    method="ngs", steps=60, sh_degree=1, checkpoint_every=20, seed=3, densify=DensifyConfig(max_gaussians=1500),
    # A surface a dozen steps old is a diffuse cloud whose half-alpha depth lies deep inside: the paper's rule.
    ngs=NGSConfig(infill=InfillConfig(levels=(8, 16), erosion_iters=(1, 2), prune_downscale=1, surface_alpha=ALPHA_MIN)),
)


def write_sphere_scan(root, masks: bool = True) -> list[np.ndarray]:
    """A posed scan folder of a striped opaque sphere; returns the true OpenCV viewmats."""
    s = sphere_surface()
    n = len(s["means"])
    stripes = (torch.sin(6 * s["means"][:, 2]) > 0).float()[:, None]
    rgb = 0.2 + 0.6 * stripes * torch.tensor([1.0, 0.6, 0.2]) + 0.1
    colors = torch.cat([rgb_to_sh(rgb)[:, None], torch.zeros(n, 3, 3)], dim=1)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    (root / "poses").mkdir()
    frames, viewmats = [], []
    for k, cam in enumerate(ring_cameras()):
        with torch.no_grad():
            img, alpha, _ = rasterization(s["means"], s["quats"], s["scales"], s["opacities"], colors,
                                          cam.viewmat[None], cam.K[None], 32, 32, sh_degree=1)
        png = np.round(img[0].clamp(0, 1).numpy()[..., ::-1] * 65535).astype(np.uint16)
        cv2.imwrite(str(root / "images" / f"f{k:02d}.png"), png)
        cv2.imwrite(str(root / "masks" / f"f{k:02d}.png"), ((alpha[0, ..., 0] > 0.5).numpy() * 255).astype(np.uint8))
        c2w_cv = np.linalg.inv(cam.viewmat.double().numpy())
        frame = {"file_path": f"images/f{k:02d}.png", "transform_matrix": (c2w_cv @ OPENGL_TO_OPENCV).tolist()}
        if masks:
            frame["mask_path"] = f"masks/f{k:02d}.png"
        frames.append(frame)
        viewmats.append(cam.viewmat.numpy())
    points = s["means"].numpy() * 1.05 + np.random.default_rng(0).normal(0, 0.02, (n, 3))
    ply = "ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nend_header\n" % n
    (root / "poses" / "cloud.ply").write_text(ply + "".join(f"{x} {y} {z}\n" for x, y, z in points))
    K = ring_cameras()[0].K
    meta = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "w": 32,
            "h": 32, "ply_file_path": "poses/cloud.ply", "frames": frames}
    (root / "poses" / "transforms.json").write_text(json.dumps(meta))
    return viewmats


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    return root, write_sphere_scan(root)


def test_dataset_turns_nerfstudio_poses_into_opencv_viewmats_and_holds_out_every_eighth(scan):
    root, viewmats = scan
    scene = load_scene(root)
    assert len(scene.test) == 2 and len(scene.train) == 12  # frames 0 and 8 of 14
    np.testing.assert_allclose(scene.test[1].viewmat.numpy(), viewmats[8], atol=1e-5)
    assert scene.test[0].image.shape == (32, 32, 3) and scene.test[0].mask.shape == (32, 32)
    assert scene.scene_scale == pytest.approx(1.1 * 6.0 * math.cos(math.radians(15)), rel=0.3)


def test_a_downscaled_view_targets_the_downscaled_object_alone_on_black(scan):
    # image x coverage is averaged, not image and mask apart: their product would darken the rim
    full, half = load_scene(scan[0]), load_scene(scan[0], downscale=2)
    for big, small in zip(full.test, half.test):
        expected = cv2.resize(big.target.numpy(), (16, 16), interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(small.target.numpy(), expected, atol=1e-5)
        assert small.mask.shape == (16, 16) and bool(((small.mask > 0) & (small.mask < 1)).any())


def test_paths_escaping_the_scan_folder_are_refused_naming_the_field(tmp_path):
    write_sphere_scan(tmp_path)
    meta = json.loads((tmp_path / "poses" / "transforms.json").read_text())
    meta["frames"][3]["mask_path"] = "../../etc/passwd"
    (tmp_path / "poses" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BadInputError, match=r"frames\[3\]\.mask_path.*outside the scan folder"):
        load_scene(tmp_path)


def make_strategy_params(scales: list[float], opacities: list[float]):
    n = len(scales)
    params = {
        "means": torch.nn.Parameter(torch.zeros(n, 3)),
        "scales": torch.nn.Parameter(torch.tensor(scales).log()[:, None].repeat(1, 3)),
        "quats": torch.nn.Parameter(torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)),
        "opacities": torch.nn.Parameter(torch.logit(torch.tensor(opacities))),
        "sh0": torch.nn.Parameter(torch.zeros(n, 1, 3)),
        "shN": torch.nn.Parameter(torch.zeros(n, 3, 3)),
    }
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    return params, optimizers


def refine_once(params, optimizers, grad_norms: list[float], budget: int = 1000):
    """One refine step of a strategy with refinement every step, fed these 2D gradients."""
    cfg = DensifyConfig(refine_start_iter=0, refine_every=1, reset_every=1000, refine_stop_iter=1000,
                        max_gaussians=budget)
    strategy = DefaultStrategy(cfg, scene_scale=1.0)
    means2d = torch.zeros(1, len(grad_norms), 2, requires_grad=True)
    means2d.grad = torch.tensor(grad_norms)[None, :, None].repeat(1, 1, 2) / math.sqrt(2) / 16  # undo x W/2
    info = {"means2d": means2d, "radii": torch.ones(1, len(grad_norms)), "width": 32, "height": 32}
    strategy.step_post_backward(params, optimizers, step=1, info=info)


def test_densification_clones_small_splits_large_and_prunes_transparent_gaussians():
    params, optimizers = make_strategy_params(scales=[0.005, 0.5, 0.005, 0.005], opacities=[0.5, 0.5, 0.5, 0.001])
    refine_once(params, optimizers, grad_norms=[1e-3, 1e-3, 1e-5, 1e-5])
    scales = torch.exp(params["scales"].detach()).max(dim=-1).values.sort().values
    # kept small #2, small #0 and its clone, two halves of the split large one; #3 pruned
    torch.testing.assert_close(scales, torch.tensor([0.005, 0.005, 0.005, 0.5 / 1.6, 0.5 / 1.6]))
    assert all(len(p) == 5 for p in params.values())
    assert optimizers["means"].param_groups[0]["params"][0] is params["means"]


def test_growth_stops_at_the_budget_keeping_the_largest_gradients():
    params, optimizers = make_strategy_params(scales=[0.005] * 4, opacities=[0.5] * 4)
    params["means"].data[:, 0] = torch.arange(4.0)
    refine_once(params, optimizers, grad_norms=[1e-3, 4e-3, 2e-3, 3e-3], budget=6)
    assert sorted(params["means"][:, 0].tolist()) == [0.0, 1.0, 1.0, 2.0, 3.0, 3.0]


def test_paced_growth_opens_the_budget_across_the_refine_window_and_grows_nothing_past_it():
    paced = DensifyConfig(refine_start_iter=100, refine_stop_iter=1100, budget_ramp=0.5)
    assert [paced.budget_at(step, 10_000) for step in (0, 100, 350, 600, 1000)] == [0, 0, 5_000, 10_000, 10_000]
    assert DensifyConfig().budget_at(0, 10_000) == 10_000  # unpaced: gsplat's behaviour
    params, optimizers = make_strategy_params(scales=[0.005] * 4, opacities=[0.5] * 4)
    strategy = DefaultStrategy(replace(paced, refine_every=1, max_gaussians=12), scene_scale=1.0)
    means2d = torch.zeros(1, 4, 2, requires_grad=True)
    means2d.grad = torch.tensor([1.0, 4.0, 2.0, 3.0])[None, :, None].repeat(1, 1, 2)
    info = {"means2d": means2d, "radii": torch.ones(1, 4), "width": 32, "height": 32}
    strategy.step_post_backward(params, optimizers, step=350, info=info)  # 6 of 12 open: room for two clones
    assert len(params["means"]) == 6


def test_the_gaussian_budget_follows_the_objects_size_on_screen_up_to_its_cap(scan, tmp_path):
    per_pixel = DensifyConfig(max_gaussians=50_000, per_object_pixel=2.5)
    assert per_pixel.budget_for(4_000.0) == 10_000
    assert per_pixel.budget_for(30_000.0) == 50_000  # capped
    assert per_pixel.budget_for(None) == 50_000  # no masks: the cap is the budget
    assert DensifyConfig(max_gaussians=7_000).budget_for(4_000.0) == 7_000  # a fixed budget stays fixed
    scene = load_scene(scan[0])
    cfg = replace(TINY, densify=replace(TINY.densify, max_gaussians=10_000, per_object_pixel=2.0))
    trainer = Trainer(scene, cfg, tmp_path)
    masked = [float(v.mask.sum()) for v in scene.train]
    assert trainer.gaussian_budget == round(2.0 * sum(masked) / len(masked))
    assert trainer.strategy.cfg.max_gaussians == trainer.gaussian_budget


def test_loss_terms_vanish_for_a_perfect_alpha_and_switch_off_by_weight():
    mask = torch.zeros(16, 16)
    mask[4:12, 4:12] = 1
    assert {k: float(v) for k, v in alpha_losses(mask, mask, LossConfig()).items()} == {"bg": 0.0, "fg": 0.0}
    assert float(alpha_losses(torch.zeros(16, 16), mask, LossConfig())["fg"]) == 1.0
    assert set(alpha_losses(mask, mask, LossConfig(fg_weight=0.0))) == {"bg"}
    binary = torch.rand(16, 16)  # with a 0/1 mask L_bg is ngs.md's sum a(1-M) / sum(1-M)
    expected = (binary * (1 - mask)).sum() / (1 - mask).sum()
    torch.testing.assert_close(alpha_losses(binary, mask, LossConfig())["bg"], expected)
    rim = mask.clone()
    rim[3, 4:12] = 0.4  # an edge row the stone covers by 40 %
    assert float(alpha_losses(rim, rim, LossConfig())["bg"]) == 0.0  # alpha = coverage is right there
    opaque_rim = rim.clone()
    opaque_rim[3, 4:12] = 1.0  # only its 0.6 beyond the coverage is stray, weighted by the 0.6 not covered
    torch.testing.assert_close(alpha_losses(opaque_rim, rim, LossConfig())["bg"], 8 * 0.6 * 0.6 / (1 - rim).sum())


def test_a_views_mask_regions_kept_from_its_first_draw_give_the_loss_worked_out_afresh(scan, tmp_path):
    trainer = Trainer(load_scene(scan[0]), TINY, tmp_path)
    view = trainer.train_views()[3]
    regions = trainer.loss_regions(3)
    assert trainer.loss_regions(3) is regions
    render, alpha = torch.rand(view.height, view.width, 3), torch.rand(view.height, view.width)
    kept, _ = total_loss(render, alpha, view.target, view.mask, TINY.loss, regions=regions)
    afresh, _ = total_loss(render, alpha, view.image * view.mask[..., None], view.mask, TINY.loss)
    assert float(kept) == float(afresh)
    torch.testing.assert_close(regions.interior, mask_regions(view.mask, TINY.loss).interior, rtol=0, atol=0)


def kernel_signatures() -> dict[str, set]:
    """Every training kernel's compiled (or cache-loaded) argument types in this process."""
    modules = (_kernels, _project_kernels, _ssim_kernels)
    return {f"{module.__name__}.{name}": set(kernel.signatures) for module in modules
            for name, kernel in vars(module).items() if isinstance(kernel, numba.core.registry.CPUDispatcher)}


def test_training_through_the_infill_and_a_held_out_render_calls_no_kernel_the_warmup_did_not(scan, tmp_path):
    """What the warm-up compiles (in its own process, beside the scan) is what training calls, so a fresh
    install's training loads every kernel from the cache."""
    exercise_kernels()
    warmed = kernel_signatures()
    trainer = Trainer(load_scene(scan[0]), TINY, tmp_path)
    for step in range(trainer.ngs.build_step + 2):
        trainer.train_step(step)
    trainer.held_out()
    assert trainer.ngs.infill is not None
    assert kernel_signatures() == warmed


def test_the_warmup_runs_in_a_process_of_its_own_and_ends_by_itself():
    process = start_kernel_warmup()
    process.join(timeout=400)  # a fresh clone compiles here, into this worker's numba cache
    assert process.exitcode == 0


def test_ngs_phases_freeze_the_surface_then_the_noise_and_recolour_every_step(scan, tmp_path):
    trainer = Trainer(load_scene(scan[0]), TINY, tmp_path)
    ngs = trainer.ngs
    for step in range(ngs.build_step):
        trainer.train_step(step)
    trainer.train_step(ngs.build_step)
    assert len(ngs.infill) > 0
    surface = {k: v.detach().clone() for k, v in trainer.model.params.items()}
    moments = {k: opt.state[trainer.model.params[k]]["exp_avg"].clone() for k, opt in trainer.optimizers.items()}
    logits = ngs.params["opacities"].detach().clone()
    colors = [ngs.colors.clone()]
    for step in range(ngs.build_step + 1, ngs.freeze_step):
        trainer.train_step(step)
        colors.append(ngs.colors.clone())
    for name, value in trainer.model.params.items():
        torch.testing.assert_close(value.detach(), surface[name], rtol=0, atol=0)
        torch.testing.assert_close(trainer.optimizers[name].state[value]["exp_avg"], moments[name], rtol=0, atol=0)
    assert not torch.equal(ngs.params["opacities"].detach()[: len(logits)], logits) or len(logits) != len(ngs.infill)
    noise_means = ngs.infill.means.clone()
    for step in range(ngs.freeze_step, ngs.freeze_step + 3):
        trainer.train_step(step)
        colors.append(ngs.colors.clone())
    assert torch.equal(ngs.infill.means, noise_means) and not ngs.params
    assert bool((ngs.noise(4)["opacities"] == 1).all())
    changed = [not torch.equal(a, b) for a, b in zip(colors, colors[1:]) if len(a) == len(b)]
    assert changed and all(changed)
    assert trainer.optimizers["means"].param_groups[0]["lr"] == pytest.approx(
        TINY.lr_means * trainer.scene.scene_scale * 0.01 ** (2 / (TINY.steps - ngs.freeze_step)))


def test_a_steps_torch_ops_run_on_one_thread_but_the_infill_is_built_on_the_whole_pool(scan, tmp_path, monkeypatch):
    import station.ngs.ngs_schedule as ngs_schedule
    import station.ngs.trainer as trainer_module

    seen = {"render": set(), "build": set()}
    render, build = trainer_module.rasterization, ngs_schedule.build_infill

    def counting_render(*args, **kwargs):
        seen["render"].add(torch.get_num_threads())
        return render(*args, **kwargs)

    def counting_build(*args, **kwargs):
        seen["build"].add(torch.get_num_threads())
        return build(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "rasterization", counting_render)
    monkeypatch.setattr(ngs_schedule, "build_infill", counting_build)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        trainer = Trainer(load_scene(scan[0]), TINY, tmp_path)
        for step in range(trainer.ngs.build_step + 2):
            trainer.train_step(step)
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert seen == {"render": {1, 2}, "build": {2}}


def test_after_the_freeze_the_foreground_alpha_loss_judges_the_surface_not_the_opaque_noise(scan, tmp_path):
    runs = {}
    for on in (True, False):
        cfg = replace(TINY, ngs=replace(TINY.ngs, fg_on_surface=on))
        trainer = Trainer(load_scene(scan[0]), cfg, tmp_path / str(on))
        for step in range(trainer.ngs.freeze_step):
            trainer.train_step(step)
        runs[on] = trainer.train_step(trainer.ngs.freeze_step)
    assert runs[True]["image"] == pytest.approx(runs[False]["image"], rel=1e-6)  # the same render
    assert runs[True]["fg"] > runs[False]["fg"] + 1e-3  # the noise no longer stands in for the surface


def test_a_nan_parameter_stops_training_naming_the_step_and_tensor(scan, tmp_path):
    trainer = Trainer(load_scene(scan[0]), TINY, tmp_path)
    trainer.train_step(0)
    trainer.model.params["scales"].data[5, 1] = float("nan")
    with pytest.raises(TrainingError, match="step 1: parameter scales holds NaN"):
        trainer.train_step(1)


def test_a_resumed_run_ends_with_the_same_parameters_as_an_uninterrupted_one(scan, tmp_path):
    scene = load_scene(scan[0])
    whole = Trainer(scene, TINY, tmp_path / "whole")
    whole.run()
    killed = Trainer(scene, replace(TINY, steps=TINY.steps), tmp_path / "resumed")
    for step in range(45):  # past the infill build; the last checkpoint is at step 40
        killed.train_step(step)
        killed.step = step + 1
        if killed.step % TINY.checkpoint_every == 0:
            killed.save_checkpoint()
    resumed = Trainer(scene, TINY, tmp_path / "resumed")
    report = resumed.run()
    assert report.resumed_from == 40
    assert len(resumed.model) == len(whole.model)
    for name, value in whole.model.params.items():
        torch.testing.assert_close(resumed.model.params[name], value)
    torch.testing.assert_close(resumed.ngs.infill.means, whole.ngs.infill.means)


def test_training_goes_on_past_the_plan_while_held_out_sos_rises_and_stops_at_the_cap(scan, tmp_path):
    scene = load_scene(scan[0])
    rising = ExtendConfig(max_extra_steps=20, sos_target=1.01, min_sos_gain=-1.0)  # any SOS counts as rising
    trainer = Trainer(scene, replace(TINY, eval_every=10, extend=rising), tmp_path / "rising")
    report = trainer.run()
    assert report.steps == TINY.steps + 20
    assert [d["extend"] for d in trainer.extensions] == [True, True, False]
    assert "cap of 20" in trainer.extensions[-1]["reason"]
    assert all(e["sos"] is not None for e in trainer.evals if e["step"] > trainer.ngs.build_step)
    flat = ExtendConfig(max_extra_steps=20, min_sos_gain=2.0, min_psnr_gain_db=100.0)
    trainer = Trainer(scene, replace(TINY, eval_every=10, extend=flat), tmp_path / "flat")
    assert trainer.run().steps == TINY.steps
    assert trainer.extensions == [{**trainer.extensions[0], "extend": False}]
    assert "stopped improving" in trainer.extensions[0]["reason"] or "reached" in trainer.extensions[0]["reason"]


def test_the_extension_decision_reads_the_last_two_evaluations():
    cfg = ExtendConfig(max_extra_steps=1_000, psnr_target_db=45.0)
    evals = [{"step": 2500, "psnr": 40.0, "sos": 0.90}, {"step": 3000, "psnr": 40.1, "sos": 0.93}]
    assert extension_decision(cfg, evals, 0, 500)["extend"]  # below target and rising
    assert not extension_decision(cfg, evals, 600, 500)["extend"]  # the next block would pass the cap
    reached = [evals[0], {**evals[1], "sos": 0.96}]
    assert not extension_decision(cfg, reached, 0, 500)["extend"]
    plateau = [evals[0], {**evals[1], "sos": 0.902}]
    assert not extension_decision(cfg, plateau, 0, 500)["extend"]
    rising_then_flat = [{"step": 2000, "psnr": 40.0, "sos": 0.85}, evals[0], {**evals[1], "sos": 0.902}]
    decision = extension_decision(cfg, rising_then_flat, 0, 500)  # one flat block after a rise: noise
    assert decision["extend"] and decision["sos_gain"] == 0.002 and decision["sos_gain_per_block"] == 0.026
    flat_twice = [{"step": 2000, "psnr": 40.0, "sos": 0.897}, evals[0], {**evals[1], "sos": 0.902}]
    assert not extension_decision(cfg, flat_twice, 0, 500)["extend"]
    learning = [evals[0], {**evals[1], "sos": 0.96, "psnr": 40.5}]
    assert extension_decision(cfg, learning, 0, 500)["extend"]  # opaque, but the photos still improve
    invisible = [{**evals[0], "psnr": 48.0}, {**evals[1], "sos": 0.96, "psnr": 48.5}]
    decision = extension_decision(cfg, invisible, 0, 500)  # a gain nobody would see in the asset
    assert not decision["extend"] and "above 45" in decision["reason"]
    before_infill = [{"step": 500, "psnr": 30.0, "sos": None}, {"step": 1000, "psnr": 30.1, "sos": None}]
    assert not extension_decision(cfg, before_infill, 0, 500)["extend"]
    assert extension_decision(ExtendConfig(), evals, 0, 500)["reason"] == "extension off"
    check_between = {"step": 2750, "psnr": 42.0, "sos": 0.99, "between_blocks": True}  # left out: gains are per block
    with_check = [evals[0], check_between, evals[1]]
    assert extension_decision(cfg, with_check, 0, 500) == extension_decision(cfg, evals, 0, 500)


def test_an_sos_just_below_its_target_reads_as_below_it_in_the_reason():
    cfg = ExtendConfig(max_extra_steps=1_000)
    evals = [{"step": 4000, "psnr": 31.39, "sos": 0.9271}, {"step": 4500, "psnr": 31.26, "sos": 0.94986}]
    assert extension_decision(cfg, evals, 0, 500)["reason"] == "SOS 0.9499 below 0.95 and still rising"
    closer = [evals[0], {**evals[1], "sos": 0.949996}]
    assert extension_decision(cfg, closer, 0, 500)["reason"] == "SOS 0.949996 below 0.95 and still rising"
    assert extension_decision(cfg, [evals[0], {**evals[1], "sos": 0.9412}], 0, 500)["reason"].startswith("SOS 0.941 ")


def test_the_early_finish_needs_the_ngs_phases_over_and_every_held_out_figure_past_its_mark():
    cfg = ExtendConfig(finish_sos=0.95, psnr_target_db=40.0)
    # the demo scan at step 2,000: SOS still rises towards 1, but the worst view leaks 1e-4 px of infill
    opaque = {"step": 2000, "psnr": 48.3, "sos": 0.989, "leak_px": 1.2e-4}
    decision = early_finish_decision(cfg, [opaque], phases_over=True)
    assert decision["finished_early"] and decision["step"] == 2000 and not decision["extend"]
    assert early_finish_decision(cfg, [opaque], phases_over=False) is None  # the infill may still change
    assert early_finish_decision(cfg, [{**opaque, "sos": 0.94}], True) is None  # below the SOS target
    # its step 1,750: the mean SOS is past the target, but one view still shows 0.003 px of green
    assert early_finish_decision(cfg, [{**opaque, "sos": 0.979, "leak_px": 3.1e-3}], True) is None
    assert early_finish_decision(cfg, [{**opaque, "psnr": 35.0}], True) is None  # the photos still improve visibly
    assert early_finish_decision(cfg, [{**opaque, "sos": None, "leak_px": None}], True) is None  # no infill
    assert early_finish_decision(cfg, [{k: v for k, v in opaque.items() if k != "leak_px"}], True) is None  # older run
    assert early_finish_decision(cfg, [{**opaque, "psnr": math.nan}], True) is None  # no held-out views
    assert early_finish_decision(ExtendConfig(), [opaque], True) is None  # off unless the preset asks


def test_a_run_opaque_before_its_plan_ends_stops_at_that_evaluation_and_stays_stopped_when_resumed(scan, tmp_path):
    scene = load_scene(scan[0])
    # every evaluation after the freeze passes
    passes = ExtendConfig(finish_sos=0.0, psnr_target_db=-math.inf, finish_max_leak_px=math.inf)
    cfg = replace(TINY, eval_every=10, extend=passes)
    trainer = Trainer(scene, cfg, tmp_path / "early")
    report = trainer.run()
    assert trainer.ngs.freeze_step <= report.steps == 20 < TINY.steps  # not at step 10: the infill was not final
    assert [d.get("finished_early") for d in trainer.extensions] == [True]
    assert trainer.losses[-1]["step"] == 20 and report.final_loss == trainer.losses[-1]["loss"]  # its last step's
    again = Trainer(scene, cfg, tmp_path / "early").run()
    assert again.resumed_from == 20 and again.steps == 20


def test_between_evaluations_an_early_end_is_looked_for_every_finish_every_steps(scan, tmp_path):
    scene = load_scene(scan[0])
    passes = ExtendConfig(finish_sos=0.0, psnr_target_db=-math.inf, finish_max_leak_px=math.inf, finish_every=4)
    trainer = Trainer(scene, replace(TINY, eval_every=10, extend=passes), tmp_path / "between")
    report = trainer.run()
    assert trainer.ngs.freeze_step == 14 and report.steps == 16  # the first check after the freeze, before step 20
    assert [e.get("between_blocks", False) for e in trainer.evals] == [False, True]
    assert trainer.extensions[0]["finished_early"] and trainer.extensions[0]["step"] == 16


def test_an_extension_is_judged_on_whole_blocks_not_on_the_checks_between_them(scan, tmp_path):
    scene = load_scene(scan[0])
    rising = ExtendConfig(max_extra_steps=10, sos_target=1.01, min_sos_gain=-1.0, finish_sos=2.0, finish_every=5)
    trainer = Trainer(scene, replace(TINY, eval_every=10, extend=rising), tmp_path / "blocks")
    trainer.run()
    at = {e["step"]: e for e in trainer.evals}
    assert at[55]["between_blocks"] and not at[60].get("between_blocks")  # checks within the plan only
    assert 65 not in at
    first = trainer.extensions[0]
    assert first["step"] == 60 and first["psnr_gain_db"] == round(at[60]["psnr"] - at[50]["psnr"], 4)


def killed_and_resumed(scene, cfg: TrainConfig, root, kill_at: int):
    """An uninterrupted run, and a run interrupted before step `kill_at` then resumed: (whole, resumed, report)."""
    whole = Trainer(scene, cfg, root / "whole")
    whole.run()
    killed = Trainer(scene, cfg, root / "killed")
    train_step = killed.train_step

    def dying(step: int) -> dict:
        if step == kill_at:
            raise KeyboardInterrupt
        return train_step(step)

    killed.train_step = dying
    with pytest.raises(KeyboardInterrupt):
        killed.run()
    resumed = Trainer(scene, cfg, root / "killed")
    report = resumed.run()
    for name, value in whole.model.params.items():
        torch.testing.assert_close(resumed.model.params[name], value)
    return whole, resumed, report


def test_a_run_killed_during_its_extension_resumes_to_the_same_end(scan, tmp_path):
    cfg = replace(TINY, eval_every=10, checkpoint_every=10,
                  extend=ExtendConfig(max_extra_steps=20, sos_target=1.01, min_sos_gain=-1.0))
    whole, resumed, report = killed_and_resumed(load_scene(scan[0]), cfg, tmp_path, kill_at=TINY.steps + 15)
    assert report.resumed_from == TINY.steps + 10 and report.steps == whole.step
    assert resumed.extensions == whole.extensions


def test_training_moves_up_a_level_once_the_coarse_level_stops_raising_full_resolution_psnr():
    cfg = ResolutionConfig(start_downscale=2)
    rising = [{"step": 100, "downscale": 2, "psnr": 30.0}, {"step": 200, "downscale": 2, "psnr": 30.5}]
    assert not resolution_decision(cfg, rising, 200, 300)["move_up"]
    assert resolution_decision(cfg, [rising[0], {**rising[1], "psnr": 30.05}], 200, 300)["move_up"]
    assert resolution_decision(cfg, [rising[0], {**rising[1], "psnr": 29.0}], 200, 300)["move_up"]  # it hurts
    assert not resolution_decision(cfg, rising[:1], 100, 300)["move_up"]  # nothing to compare with yet
    assert resolution_decision(cfg, rising, 300, 300)["move_up"]  # the longest a level may last
    assert resolution_decision(cfg, [{**rising[0], "psnr": float("nan")}], 100, 300)["move_up"]  # nothing held out
    with pytest.raises(BadInputError, match="power of two"):
        ResolutionConfig(start_downscale=3)


COARSE_START = replace(TINY, eval_every=30, resolution=ResolutionConfig(
    start_downscale=2, check_every=10 / TINY.steps, max_level_steps=30 / TINY.steps, min_psnr_gain_db=-1e9))


def test_a_coarse_start_trains_on_downscaled_views_and_ends_at_full_resolution(scan, tmp_path):
    scene, half = load_scene(scan[0]), load_scene(scan[0], downscale=2)
    for view, expected in zip([downscaled_view(v, 2) for v in scene.train], half.train):
        torch.testing.assert_close(view.image, expected.image, rtol=0, atol=0)
        torch.testing.assert_close(view.mask, expected.mask, rtol=0, atol=0)
        torch.testing.assert_close(view.K, expected.K, rtol=0, atol=0)
    trainer = Trainer(scene, COARSE_START, tmp_path)
    seen = []
    train_step = trainer.train_step
    trainer.train_step = lambda step: seen.append(trainer.train_views()[0].width) or train_step(step)
    scored = {}  # step: held-out PSNR, the full-resolution score of the test views
    held_out_psnr = trainer.held_out_psnr
    trainer.held_out_psnr = lambda *a: scored.setdefault(trainer.step, held_out_psnr(*a))
    report = trainer.run()
    assert seen == [16] * 30 + [32] * 30  # never gaining below -1e9 dB, it moves up at the 30-step limit
    assert [(c["step"], c["downscale"], c["move_up"]) for c in trainer.resolution_checks] == [
        (10, 2, False), (20, 2, False), (30, 2, True)]
    assert all(c["psnr"] == round(scored[c["step"]], 4) for c in trainer.resolution_checks)
    write_model(trainer, report)
    written = json.loads((tmp_path / "train_metrics.json").read_text())["resolution"]
    assert written["start_downscale"] == 2 and written["final_downscale"] == 1 and len(written["checks"]) == 3
    plateau = replace(COARSE_START, resolution=replace(COARSE_START.resolution, min_psnr_gain_db=1e9))
    trainer = Trainer(scene, plateau, tmp_path / "plateau")
    trainer.run()
    assert [(c["step"], c["move_up"]) for c in trainer.resolution_checks] == [(10, False), (20, True)]
    assert "stopped paying" in trainer.resolution_checks[-1]["reason"]


@pytest.mark.parametrize("kill_at", [25, 45], ids=["while coarse", "after moving up"])
def test_a_run_killed_around_a_resolution_change_resumes_to_the_same_end(scan, tmp_path, kill_at):
    cfg = replace(COARSE_START, checkpoint_every=10)
    whole, resumed, report = killed_and_resumed(load_scene(scan[0]), cfg, tmp_path, kill_at=kill_at)
    assert report.resumed_from == kill_at // 10 * 10 and resumed.level_downscale == 1
    assert resumed.resolution_checks == whole.resolution_checks


def test_a_checkpoint_from_another_configuration_is_refused(scan, tmp_path):
    scene = load_scene(scan[0])
    Trainer(scene, replace(TINY, steps=20), tmp_path).run()
    with pytest.raises(TrainingError, match="another training configuration"):
        Trainer(scene, TINY, tmp_path).run()


def test_trained_ngs_model_is_written_and_scored_end_to_end(tmp_path):
    write_sphere_scan(tmp_path)
    cfg = replace(TINY, steps=300, checkpoint_every=300, eval_every=150)
    trainer = Trainer(load_scene(tmp_path), cfg, tmp_path / "model")
    report = trainer.run()
    write_model(trainer, report)
    assert report.num_infill > 0 and (tmp_path / "model" / "infill.pt").is_file()
    held_out = json.loads((tmp_path / "model" / "train_metrics.json").read_text())["held_out"]
    assert [e["step"] for e in held_out] == [150, 300] and held_out[-1]["psnr"] > 20
    result = evaluate_scan(tmp_path)
    assert result["infill_source"] == "ngs"
    assert result["psnr"] > 20
    assert held_out[-1]["sos"] == pytest.approx(result["sos"], abs=1e-6)  # the curve ends where the score is
    assert result["sos"] > 0.1  # a 300-step run: the infill is already mostly hidden (T < 0.1)
    assert len(list((tmp_path / "model" / "sos").glob("*.png"))) == 2
    # the written splat keeps the SH bands the held-out views asked for, and is scored as written
    sh = json.loads((tmp_path / "model" / "train_metrics.json").read_text())["sh_degree"]
    assert sh["trained"] == 1 and set(sh["held_out_psnr"]) == {"0", "1"}
    written = torch.load(tmp_path / "model" / "surface.pt", weights_only=True)["params"]["shN"]
    assert written.shape[1] == (sh["kept"] + 1) ** 2 - 1
    assert result["psnr"] == pytest.approx(sh["held_out_psnr"][str(sh["kept"])], abs=1e-3)
    write_inria_ply(tmp_path / "elsewhere.ply", trainer.model)
    foreign = score_splat(tmp_path, tmp_path / "elsewhere.ply")
    assert foreign["infill_source"] == "ngs"
    assert foreign["sos"] == pytest.approx(result["sos"], abs=1e-6)
    assert len(list((tmp_path / "model" / "sos_elsewhere").glob("*.png"))) == 2


def test_the_written_sh_degree_is_the_lowest_the_held_out_views_do_not_miss():
    flat = {0: 40.00, 1: 40.05, 2: 40.08, 3: 40.02}
    assert sh_degree_choice(3, flat[3], flat.__getitem__, tolerance_db=0.1)["kept"] == 0
    glossy = {0: 36.0, 1: 39.0, 2: 39.95, 3: 40.0}
    choice = sh_degree_choice(3, glossy[3], glossy.__getitem__, tolerance_db=0.1)
    assert choice["kept"] == 2 and choice["held_out_psnr"] == {"0": 36.0, "1": 39.0, "2": 39.95, "3": 40.0}
    nothing_held_out = sh_degree_choice(1, float("nan"), lambda degree: pytest.fail("rendered"), tolerance_db=0.1)
    assert nothing_held_out["kept"] == 1
    params = {"sh0": torch.zeros(5, 1, 3), "shN": torch.arange(5 * 15 * 3.0).reshape(5, 15, 3)}
    cut = cut_to_degree(params, 1)
    assert cut["shN"].shape == (5, 3, 3) and torch.equal(cut["shN"], params["shN"][:, :3])


def test_methods_pick_their_losses_and_unknown_names_are_refused():
    assert make_config("3dgs", "fast").loss.fg_weight == 0 and make_config("3dgs", "fast").loss.bg_weight == 0
    assert make_config("alpha", "fast").loss.fg_weight == 1 and make_config("ngs", "paper").steps == 30_000
    with pytest.raises(BadInputError, match="unknown method"):
        make_config("nerf", "fast")
    with pytest.raises(BadInputError, match="unknown preset"):
        make_config("ngs", "slow")
