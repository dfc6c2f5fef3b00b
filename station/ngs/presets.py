"""Named training configurations: `paper` (the 30k-step schedule), `fast` (demo and CI on a CPU) and
`tiny` (a smoke test: proves the pipeline runs end to end, not that the model is good). Any of
them with `-safe` appended is the batch runner's retry after a diverged or out-of-memory run.

A method picks the losses and whether NGS runs: `3dgs` is image loss only (masked ground truth,
black background), `alpha` adds L_bg and L_fg, `ngs` adds the noise infill on top of `alpha`.
"""

from __future__ import annotations

from dataclasses import replace

from station.ngs.conventions import ALPHA_MIN
from station.ngs.infill import InfillConfig
from station.ngs.losses import LossConfig
from station.ngs.ngs_schedule import NGSConfig
from station.ngs.preset_names import SAFER_SUFFIX, check_names
from station.ngs.resolution import ResolutionConfig
from station.ngs.stopping import ExtendConfig
from station.ngs.strategy import DensifyConfig
from station.ngs.trainer import TrainConfig


def paper_preset() -> TrainConfig:
    return TrainConfig(steps=30_000, sh_degree=3, downscale=1, checkpoint_every=1_000, eval_every=2_000)


def fast_preset() -> TrainConfig:
    """Short CPU run (demo, CI, the station's default); every schedule keeps the paper's proportions.

    Sized by held-out error against training size (docs/method.md): a larger Gaussian budget bought no
    held-out PSNR, steps bought SOS. So the plan is a guide: a scene opaque early ends early, one still
    gaining SOS trains on (stopping.py), the budget follows the stone's size on screen
    (DensifyConfig.per_object_pixel), colour is written at the lowest SH degree its held-out views need
    (sh_degree.py), and training starts coarse and moves up once that stops paying (resolution.py).
    """
    return TrainConfig(
        steps=2_500,
        sh_degree=1,
        downscale=1,
        checkpoint_every=250,
        eval_every=500,
        densify=DensifyConfig(max_gaussians=60_000, per_object_pixel=2.65),
        ngs=NGSConfig(infill=InfillConfig(levels=(32, 64), erosion_iters=(3, 4))),
        extend=ExtendConfig(max_extra_steps=3_000, finish_sos=0.95, finish_every=250),
        resolution=ResolutionConfig(start_downscale=2),
    )


def tiny_preset() -> TrainConfig:
    """Smoke test for tiny scans (batch tests, benches): seconds on a CPU; its models rarely pass the gate."""
    return TrainConfig(
        steps=300,
        sh_degree=0,
        downscale=1,
        checkpoint_every=50,
        densify=DensifyConfig(max_gaussians=2_000),
        # Built at mid-run, once the few steps have given the surface some opacity, eroded once, and pruned to
        # the surface's first faint Gaussian (the paper's rule): an earlier build, deeper erosion or pruning
        # to where a 150-step surface turns opaque leaves a 16/32 grid empty, and export refuses an empty infill.
        ngs=NGSConfig(build_at=0.5, freeze_at=0.55,
                      infill=InfillConfig(levels=(16, 32), erosion_iters=(1, 1), surface_alpha=ALPHA_MIN)),
    )


PRESETS = {"paper": paper_preset, "fast": fast_preset, "tiny": tiny_preset}  # by name: preset_names.PRESET_NAMES


def safer(cfg: TrainConfig) -> TrainConfig:
    """Half the step sizes (divergence), half the Gaussian budget and half the resolution (memory)."""
    return replace(
        cfg,
        lr_means=cfg.lr_means / 2,
        lr_scales=cfg.lr_scales / 2,
        lr_quats=cfg.lr_quats / 2,
        lr_opacities=cfg.lr_opacities / 2,
        lr_sh0=cfg.lr_sh0 / 2,
        lr_shN=cfg.lr_shN / 2,
        downscale=cfg.downscale * 2,
        densify=replace(cfg.densify, max_gaussians=max(1, cfg.densify.max_gaussians // 2),
                        per_object_pixel=cfg.densify.per_object_pixel / 2),
    )


def make_config(method: str, preset: str) -> TrainConfig:
    check_names(method, preset)
    cfg = PRESETS[preset.removesuffix(SAFER_SUFFIX)]()
    if preset.endswith(SAFER_SUFFIX):
        cfg = safer(cfg)
    if method == "3dgs":
        return replace(cfg, method="3dgs", loss=LossConfig(bg_weight=0.0, fg_weight=0.0))
    return replace(cfg, method=method)
