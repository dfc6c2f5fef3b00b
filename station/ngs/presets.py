"""Named training configurations: `paper` (the 30k-step schedule) and `fast` (demo and CI on a CPU).

A method picks the losses and whether NGS runs: `3dgs` is image loss only (masked ground truth,
black background), `alpha` adds L_bg and L_fg, `ngs` adds the noise infill on top of `alpha`.
"""

from __future__ import annotations

from dataclasses import replace

from station.errors import BadInputError
from station.ngs.infill import InfillConfig
from station.ngs.losses import LossConfig
from station.ngs.ngs_schedule import NGSConfig
from station.ngs.strategy import DensifyConfig
from station.ngs.trainer import TrainConfig

METHODS = ("3dgs", "alpha", "ngs")


def paper_preset() -> TrainConfig:
    return TrainConfig(steps=30_000, sh_degree=3, downscale=1, checkpoint_every=1_000, eval_every=2_000)


def fast_preset() -> TrainConfig:
    """Short CPU run: degree-1 colour, three infill levels; all schedules keep the paper's proportions."""
    return TrainConfig(
        steps=3_000,
        sh_degree=1,
        downscale=1,
        checkpoint_every=250,
        eval_every=500,
        densify=DensifyConfig(max_gaussians=50_000),
        ngs=NGSConfig(infill=InfillConfig(levels=(32, 64, 128), erosion_iters=(3, 4, 5))),
    )


PRESETS = {"paper": paper_preset, "fast": fast_preset}


def make_config(method: str, preset: str) -> TrainConfig:
    if method not in METHODS:
        raise BadInputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if preset not in PRESETS:
        raise BadInputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    cfg = PRESETS[preset]()
    if method == "3dgs":
        return replace(cfg, method="3dgs", loss=LossConfig(bg_weight=0.0, fg_weight=0.0))
    return replace(cfg, method=method)
