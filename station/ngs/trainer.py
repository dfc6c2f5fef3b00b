"""The training loop: one image per step, Adam, and hooks for densification and the NGS phases.

Strategy code (strategy.py, ngs_schedule.py) decides what grows, what is pruned and what is
frozen; this file only renders, takes the loss, steps the optimisers and keeps checkpoints so a
killed run continues where it stopped.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch

from station.errors import BadInputError, TrainingError
from station.ngs.checkpoint_io import load_training_checkpoint
from station.ngs.dataset import SceneData, View, downscaled_view
from station.ngs.gaussians import Gaussians
from station.ngs.infill import Camera
from station.ngs.losses import LossConfig, MaskRegions, mask_regions, total_loss
from station.ngs.ngs_schedule import NGSConfig, NGSPhases
from station.ngs.raster import rasterization, torch_threads
from station.ngs.resolution import ResolutionConfig, resolution_decision
from station.ngs.sos import held_out_sos
from station.ngs.stopping import BETWEEN_BLOCKS, ExtendConfig, early_finish_decision, extension_decision
from station.ngs.strategy import DefaultStrategy, DensifyConfig, DensifyState
from station.scanfolder import atomic_write_with

Method = Literal["3dgs", "alpha", "ngs"]
CHECKPOINT = "checkpoint.pt"
STEP_TORCH_THREADS = 1  # torch's pool inside a training step (bench/step_threads.py): its ops are small
log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    method: Method = "ngs"
    steps: int = 30_000
    sh_degree: int = 3
    # written degree: the lowest whose held-out PSNR is within this of the trained degree's (sh_degree.py)
    sh_tolerance_db: float = 0.1
    sh_degree_every: float = 1_000 / 30_000  # raise the SH degree by one every this fraction of the run
    lr_means: float = 1.6e-4  # x scene_scale, decayed to 1%
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    downscale: int = 1
    checkpoint_every: int = 500
    eval_every: int = 0  # held-out PSNR and SOS every this many steps (0: off), the speed-against-error evidence
    seed: int = 0
    backend: str = "auto"
    device: str = "auto"  # where every training tensor lives: "auto" is cuda when available, else cpu
    loss: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)  # in 30k-step units, scaled to `steps`
    ngs: NGSConfig = field(default_factory=NGSConfig)
    extend: ExtendConfig = field(default_factory=ExtendConfig)  # past `steps`, or an early end (stopping.py)
    resolution: ResolutionConfig = field(default_factory=ResolutionConfig)  # coarse-to-fine (resolution.py)


@dataclass
class TrainReport:
    method: str
    steps: int
    seconds: float
    num_gaussians: int
    num_infill: int
    final_loss: float
    resumed_from: int
    model_dir: str
    device: str  # where it trained (TrainConfig.device resolved)


def object_pixels(scene: SceneData) -> float | None:
    """Pixels the object covers in the mean masked training view; None without masks."""
    areas = [float(view.mask.sum()) for view in scene.train if view.mask is not None]
    return sum(areas) / len(areas) if areas else None


def training_device(name: str) -> torch.device:
    """The device `TrainConfig.device` names; "auto" is CUDA when torch sees a GPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise BadInputError(f"training device {name!r} is not a torch device ({exc})") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise BadInputError(f"training device {name!r}: torch {torch.__version__} sees no CUDA device")
    return device


def check_finite(step: int, named: dict[str, torch.Tensor]) -> None:
    """Every step, so a diverged run stops before its checkpoint; numpy on CPU, where it costs a fifth of torch's."""
    for name, tensor in named.items():
        values = tensor.detach()
        finite = np.isfinite(values.numpy()).all() if values.device.type == "cpu" else torch.isfinite(values).all()
        if not bool(finite):
            raise TrainingError(f"step {step}: {name} holds NaN or inf; training stopped")


class Trainer:
    def __init__(self, scene: SceneData, cfg: TrainConfig, model_dir: Path, inputs: str = ""):
        """`inputs` fingerprints the posed views; a checkpoint is resumed only from the same fingerprint."""
        self.device = training_device(cfg.device)
        self.cfg, self.model_dir, self.inputs = cfg, Path(model_dir), inputs
        self.scene = scene.to(self.device)
        self.model = Gaussians.from_points(scene.points, scene.point_colors, cfg.sh_degree, cfg.seed, self.device)
        self.optimizers = self._make_optimizers()
        densify = cfg.densify.scaled(cfg.steps)
        self.gaussian_budget = densify.budget_for(object_pixels(scene))
        self.strategy = DefaultStrategy(replace(densify, max_gaussians=self.gaussian_budget), scene.scene_scale,
                                        cfg.seed)
        self.ngs = NGSPhases(cfg.ngs, cfg.steps, cfg.seed, self.device) if cfg.method == "ngs" else None
        self.generator = torch.Generator().manual_seed(cfg.seed)  # CPU: the same draws on every device
        self.cameras = [Camera(v.viewmat, v.K, v.width, v.height) for v in self.scene.train]
        self.resolution_checks: list[dict] = []  # every check of the training level; the level follows from them
        self._levels: dict[int, list[View]] = {1: self.scene.train}
        self._regions: dict[tuple[int, int], MaskRegions] = {}  # (level, view index) -> its mask's loss regions
        self.step = 0
        self.seconds = 0.0
        self.losses: list[dict] = []
        self.evals: list[dict] = []
        self.extensions: list[dict] = []

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        lrs = {
            "means": self.cfg.lr_means * self.scene.scene_scale,
            "scales": self.cfg.lr_scales,
            "quats": self.cfg.lr_quats,
            "opacities": self.cfg.lr_opacities,
            "sh0": self.cfg.lr_sh0,
            "shN": self.cfg.lr_shN,
        }
        # fused: one kernel per parameter instead of a dozen small ops, which cost most beside numba's threads
        return {name: torch.optim.Adam([p], lr=lrs[name], eps=1e-15, fused=True)
                for name, p in self.model.params.items()}

    @property
    def level_downscale(self) -> int:
        """The training level, relative to the scene's views: the start, halved at every move up so far."""
        moves = sum(check["move_up"] for check in self.resolution_checks)
        return max(1, self.cfg.resolution.start_downscale >> moves)

    @property
    def level_start(self) -> int:
        """The step the current level began at."""
        return max((check["step"] for check in self.resolution_checks if check["move_up"]), default=0)

    def train_views(self) -> list[View]:
        """The training views at the current level, downscaled once per level."""
        if self.level_downscale not in self._levels:
            self._levels[self.level_downscale] = [downscaled_view(v, self.level_downscale) for v in self.scene.train]
        return self._levels[self.level_downscale]

    def loss_regions(self, index: int) -> MaskRegions | None:
        """The loss regions of training view `index` at the current level, worked out on its first draw."""
        key = (self.level_downscale, index)
        if key not in self._regions:
            mask = self.train_views()[index].mask
            if mask is None:
                return None
            self._regions[key] = mask_regions(mask, self.cfg.loss)
        return self._regions[key]

    @property
    def target_steps(self) -> int:
        """The planned steps plus one block of eval_every for every extension decided so far, or the step the
        run finished early at."""
        finished = [d["step"] for d in self.extensions if d.get("finished_early")]
        if finished:
            return finished[0]
        return self.cfg.steps + self.cfg.eval_every * sum(d["extend"] for d in self.extensions)

    def sh_degree_at(self, step: int) -> int:
        every = max(1, round(self.cfg.sh_degree_every * self.cfg.steps))
        return min(step // every, self.cfg.sh_degree)

    def means_lr_at(self, step: int) -> float:
        step = min(step, self.cfg.steps)  # past the plan (an extension) the rate stays at its final 1%
        factor = self.ngs.means_lr_factor(step) if self.ngs else 0.01 ** (step / self.cfg.steps)
        return self.cfg.lr_means * self.scene.scene_scale * factor

    def train_step(self, step: int) -> dict[str, float]:
        """One image, one Adam step; densification and NGS hooks around it. torch's ops run on
        STEP_TORCH_THREADS, but for the step that builds the infill: it keeps the whole pool."""
        building = bool(self.ngs and self.ngs.builds_infill(step))
        with torch_threads(torch.get_num_threads() if building else STEP_TORCH_THREADS):
            return self._train_step(step)

    def _train_step(self, step: int) -> dict[str, float]:
        check_finite(step, {f"parameter {k}": v for k, v in self.model.params.items()})
        views = self.train_views()
        index = int(torch.randint(len(views), (1,), generator=self.generator, device="cpu"))
        view = views[index]
        frozen = bool(self.ngs and self.ngs.surface_frozen(step))
        for p in self.model.params.values():
            p.requires_grad_(not frozen)
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr_at(step)
        g = self.model.activated()
        if self.ngs:  # the same activations, detached: the infill is built from the surface's current state
            self.ngs.step_pre(step, {k: v.detach() for k, v in g.items()}, self.cameras)
        noise = self.ngs.noise(g["colors"].shape[1]) if self.ngs else None
        surface_fg = bool(noise is not None and self.ngs.fg_on_surface(step))
        is_noise = torch.cat([torch.zeros(len(self.model), 1, device=self.device),
                              torch.ones(len(noise["means"]), 1, device=self.device)]) if surface_fg else None
        if noise is not None:
            g = {k: torch.cat([g[k], noise[k]]) for k in g}
        colors, alphas, meta = rasterization(
            g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            view.viewmat[None], view.K[None], view.width, view.height,
            sh_degree=self.sh_degree_at(step), extra=is_noise, backend=self.cfg.backend,
        )  # [1, H, W, 3 (+1: the noise's weight)], [1, H, W, 1]
        if not frozen:
            self.strategy.step_pre_backward(meta)
        # views and a split, not indexing: each index's backward zero-fills an image-sized gradient and copies in
        rgb, noise_weight = colors.squeeze(0).split(3, dim=-1) if surface_fg else (colors.squeeze(0), None)
        alpha = alphas.squeeze(0).squeeze(-1)
        surface_alpha = alpha - noise_weight.squeeze(-1) if surface_fg else None
        loss, terms = total_loss(rgb, alpha, view.target, view.mask, self.cfg.loss, surface_alpha,
                                 self.loss_regions(index))
        check_finite(step, {"loss": loss})
        if loss.requires_grad:  # False only when the surface is frozen and no noise survived
            loss.backward()
        if not frozen:
            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            self.strategy.step_post_backward(self.model.params, self.optimizers, step, meta)
        if self.ngs:
            self.ngs.step_post_backward(step)
        terms["loss"] = float(loss.detach())
        return terms

    def run(self, progress: Callable[[int, dict], None] | None = None) -> TrainReport:
        resumed_from = self.load_checkpoint()
        started = time.perf_counter() - self.seconds
        while self.step < self.target_steps:
            terms = self.train_step(self.step)
            self.step += 1
            self.seconds = time.perf_counter() - started
            last = self.step == self.target_steps
            if self.level_downscale > 1 and self.step % self.cfg.resolution.check_steps(self.cfg.steps) == 0:
                self._check_resolution()
            on_block = bool(self.cfg.eval_every) and (self.step % self.cfg.eval_every == 0 or last)
            if on_block or self._finish_check_due():
                between = {} if on_block else {BETWEEN_BLOCKS: True}
                self.evals.append({"step": self.step, "seconds": round(self.seconds, 2), **between, **self.held_out()})
                if last:
                    self._decide_extension()
                else:
                    last = self._finish_early()
            if self.step % 100 == 0 or last:  # after the evaluation: an early finish makes this step the last
                self.losses.append({"step": self.step, "seconds": round(self.seconds, 2), **terms})
                if progress:
                    progress(self.step, terms)
            if self.step % self.cfg.checkpoint_every == 0 or last:
                self.save_checkpoint()
        return TrainReport(
            method=self.cfg.method,
            steps=self.step,
            seconds=round(self.seconds, 2),
            num_gaussians=len(self.model),
            num_infill=len(self.ngs.infill) if self.ngs and self.ngs.infill is not None else 0,
            final_loss=self.losses[-1]["loss"] if self.losses else float("nan"),
            resumed_from=resumed_from,
            model_dir=str(self.model_dir),
            device=str(self.device),
        )

    def _check_resolution(self) -> None:
        """Score the held-out views at full resolution and halve the downscale once this level stops paying."""
        check = {"step": self.step, "downscale": self.level_downscale, "psnr": round(self.held_out_psnr(), 4)}
        at_level = [c for c in self.resolution_checks if c["downscale"] == self.level_downscale] + [check]
        decision = resolution_decision(self.cfg.resolution, at_level, self.step - self.level_start,
                                       self.cfg.resolution.level_limit(self.cfg.steps))
        self.resolution_checks.append(decision)

    def _finish_early(self) -> bool:
        decision = early_finish_decision(self.cfg.extend, self.evals, self._ngs_phases_over())
        if decision is not None:
            self.extensions.append(decision)
        return decision is not None

    def _ngs_phases_over(self) -> bool:
        """The infill is final: from here on an early end can be decided."""
        return self.ngs is not None and self.step >= self.ngs.freeze_step

    def _finish_check_due(self) -> bool:
        """Whether to look for an early end at this step, between the evaluations (ExtendConfig.finish_every)."""
        every = self.cfg.extend.finish_every
        return (every > 0 and self.cfg.extend.finish_sos is not None and self._ngs_phases_over()
                and self.step < self.cfg.steps and self.step % every == 0)

    def _decide_extension(self) -> None:
        self.extensions.append(extension_decision(self.cfg.extend, self.evals, self.target_steps - self.cfg.steps,
                                                  self.cfg.eval_every))

    def held_out(self) -> dict[str, float | None]:
        """Held-out PSNR, and SOS and the largest leak against the training infill once NGS has built one
        (else None)."""
        infill = self.ngs.infill if self.ngs else None
        sos = leak_px = None
        if infill is not None:
            surface = {k: v.detach() for k, v in self.model.activated().items()}
            sos, leak_px = held_out_sos(surface, infill, self.scene.test, self.cfg.backend)
        return {"psnr": self.held_out_psnr(), "sos": sos, "leak_px": leak_px}

    def held_out_psnr(self, sh_degree: int | None = None) -> float:
        """Mean PSNR of the surface on the held-out views (render clamped, against the view's target, both
        weighted by the mask), its colour cut to `sh_degree` (default: the trained degree)."""
        if not self.scene.test:
            return float("nan")
        g = {k: v.detach() for k, v in self.model.activated().items()}
        values = []
        for view in self.scene.test:
            with torch.no_grad():
                colors, _, _ = rasterization(
                    g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], view.viewmat[None],
                    view.K[None], view.width, view.height,
                    sh_degree=self.cfg.sh_degree if sh_degree is None else sh_degree, backend=self.cfg.backend,
                )
            mask = view.mask[..., None] if view.mask is not None else torch.ones(1, device=self.device)
            mse = float(((colors[0].clamp(0, 1) - view.target) * mask).square().mean())
            values.append(10 * math.log10(1 / max(mse, 1e-12)))
        return sum(values) / len(values)

    # Checkpoints ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "config": asdict(self.cfg),
            "inputs": self.inputs,
            "step": self.step,
            "seconds": self.seconds,
            "model": self.model.state_dict(),
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "strategy": self.strategy.state.state_dict(),
            "strategy_generator": self.strategy.generator.get_state(),
            "ngs": self.ngs.state_dict() if self.ngs else None,
            "generator": self.generator.get_state(),
            "losses": list(self.losses),
            "evals": list(self.evals),
            "extensions": list(self.extensions),
            "resolution": {"checks": list(self.resolution_checks)},
        }

    def save_checkpoint(self) -> None:
        state = self.state_dict()
        atomic_write_with(self.model_dir / CHECKPOINT, lambda tmp: torch.save(state, tmp))

    def load_checkpoint(self) -> int:
        """Continue from model/checkpoint.pt if it was written by the same configuration on the same views."""
        path = self.model_dir / CHECKPOINT
        if not path.is_file():
            return 0
        state = load_training_checkpoint(path)  # untrusted: weights only, layout checked
        if state.get("inputs", "") != self.inputs:
            log.warning("%s: written from other posed views; training starts over", path)
            return 0
        if state["config"] != asdict(self.cfg):
            raise TrainingError(f"{path}: written by another training configuration; delete it to start over")
        self.model = Gaussians.from_state_dict(state["model"]).to(self.device)
        self.optimizers = self._make_optimizers()
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        self.strategy.state = DensifyState.from_state_dict(
            {k: v.to(self.device) if torch.is_tensor(v) else v for k, v in state["strategy"].items()})
        self.strategy.generator.set_state(state["strategy_generator"])
        if self.ngs:
            self.ngs.load_state_dict(state["ngs"])
        self.generator.set_state(state["generator"])
        self.step, self.seconds = state["step"], state["seconds"]
        self.losses, self.evals = list(state["losses"]), list(state["evals"])
        self.extensions = list(state["extensions"])
        self.resolution_checks = list(state["resolution"]["checks"])
        return self.step

