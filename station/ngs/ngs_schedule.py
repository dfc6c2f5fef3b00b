"""The NGS phases as a strategy with hooks, kept out of the training loop.

1. [0, build): ordinary surface training.
2. At `build`: build the infill (infill.py).
3. [build, freeze): fine-tune only the noise opacities (from 0.1, lr 5e-2) with the surface frozen,
   optimizer state included; prune noise with opacity < 0.01 at a fixed interval.
4. [freeze, end): noise opacity 1 and frozen; the means learning rate restarts from its initial
   value (times scene_scale) and decays to 1% by the end.
Noise colours are re-drawn from RGBCMY every step from `build` on, so the surface cannot learn to
rely on the noise's colour: only covering it pays. All steps scale with the run length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from station.ngs.conventions import rgb_to_sh
from station.ngs.infill import Camera, Infill, InfillConfig, build_infill, random_rgbcmy
from station.ngs.strategy import remove


@dataclass
class NGSConfig:
    build_at: float = 6_000 / 30_000  # fractions of the run
    freeze_at: float = 7_000 / 30_000
    prune_every: float = 100 / 30_000
    noise_start_opacity: float = 0.1
    noise_lr: float = 5e-2
    noise_prune_opacity: float = 0.01
    lr_reset: bool = True  # ablation switch "no LR reset"
    recolour: bool = True  # ablation switch "no colour reset"
    # Once the noise is opaque it fills the mask's alpha by itself, and L_fg on the rendered alpha falls
    # silent. Ours then judges the surface's own alpha (rendered alpha minus the noise's weight), so the
    # pull towards an opaque surface continues to the end. False is the reference's behaviour.
    fg_on_surface: bool = True
    infill: InfillConfig = field(default_factory=InfillConfig)


class NGSPhases:
    """Owns the infill and its optimiser; the trainer asks it what is frozen and what to render."""

    def __init__(self, cfg: NGSConfig, total_steps: int, seed: int = 0, device: torch.device | str = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)  # the infill follows the surface it is built from; colours too
        self.total_steps = total_steps
        self.build_step = max(1, round(cfg.build_at * total_steps))
        self.freeze_step = max(self.build_step + 1, round(cfg.freeze_at * total_steps))
        self.prune_every = max(1, round(cfg.prune_every * total_steps))
        self.generator = torch.Generator().manual_seed(seed + 1)
        self.infill: Infill | None = None
        self.params: dict[str, torch.nn.Parameter] = {}  # {"opacities": [M] logits} while fine-tuning
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.colors: torch.Tensor | None = None  # [M, 3] RGB
        self.history: list[dict] = []

    def surface_frozen(self, step: int) -> bool:
        return self.build_step <= step < self.freeze_step

    def fg_on_surface(self, step: int) -> bool:
        """L_fg looks at the surface's own alpha from the freeze on (see NGSConfig.fg_on_surface)."""
        return self.cfg.fg_on_surface and self.infill is not None and step >= self.freeze_step

    def means_lr_factor(self, step: int) -> float:
        """Exponential decay to 1%, restarted at the freeze when the LR reset is on."""
        start = self.freeze_step if (self.cfg.lr_reset and step >= self.freeze_step) else 0
        return 0.01 ** ((step - start) / max(1, self.total_steps - start))

    def builds_infill(self, step: int) -> bool:
        return step == self.build_step and self.infill is None

    def step_pre(self, step: int, surface: dict[str, torch.Tensor], cameras: list[Camera]) -> None:
        """Build the infill at `build`, freeze the noise at `freeze`, recolour the noise."""
        if self.builds_infill(step):
            self.infill = build_infill(surface, cameras, self.cfg.infill)
            logit = math.log(self.cfg.noise_start_opacity / (1 - self.cfg.noise_start_opacity))
            self._set_trainable(torch.full((len(self.infill),), logit, device=self.device))
            self.colors = random_rgbcmy(len(self.infill), self.generator, self.device)
            self.history.append({"step": step, "event": "build", "num_infill": len(self.infill)})
        if step == self.freeze_step and self.params:
            self.params, self.optimizers = {}, {}
            self.history.append({"step": step, "event": "freeze", "num_infill": len(self.infill)})
        if self.infill is not None and self.cfg.recolour and step > self.build_step:
            self.colors = random_rgbcmy(len(self.infill), self.generator, self.device)

    def _set_trainable(self, logits: torch.Tensor) -> None:
        param = torch.nn.Parameter(logits)
        self.params = {"opacities": param}
        self.optimizers = {"opacities": torch.optim.Adam([param], lr=self.cfg.noise_lr, eps=1e-15, fused=True)}

    def noise(self, sh_bases: int) -> dict[str, torch.Tensor] | None:
        """Rasteriser inputs of the noise, colours as SH [M, sh_bases, 3] (DC only)."""
        if self.infill is None:
            return None
        opacity = torch.sigmoid(self.params["opacities"]) if self.params else torch.ones(len(self.infill), device=self.device)
        out = self.infill.gaussians(1.0)
        out["opacities"] = opacity
        sh = torch.zeros(len(self.infill), sh_bases, 3, device=self.device)
        sh[:, 0] = rgb_to_sh(self.colors)
        out["colors"] = sh
        return out

    def step_post_backward(self, step: int) -> None:
        """Adam step on the noise opacities, then the periodic low-opacity prune."""
        if not self.params:
            return
        self.optimizers["opacities"].step()
        self.optimizers["opacities"].zero_grad(set_to_none=True)
        if (step - self.build_step) % self.prune_every == 0 and step > self.build_step:
            low = torch.sigmoid(self.params["opacities"].detach()) < self.cfg.noise_prune_opacity
            if low.any():
                remove(self.params, self.optimizers, low)
                self.infill = self.infill.select(~low)
                self.colors = self.colors[~low]
                self.history.append({"step": step, "event": "prune", "removed": int(low.sum())})

    def state_dict(self) -> dict:
        return {
            "infill": None if self.infill is None else self.infill.state_dict(),
            "logits": self.params["opacities"].detach().clone() if self.params else None,
            "optimizer": self.optimizers["opacities"].state_dict() if self.optimizers else None,
            "colors": self.colors,
            "generator": self.generator.get_state(),
            "history": list(self.history),
        }

    def load_state_dict(self, data: dict) -> None:
        self.infill = None if data["infill"] is None else Infill.from_state_dict(data["infill"]).to(self.device)
        self.params, self.optimizers = {}, {}
        if data["logits"] is not None:
            self._set_trainable(data["logits"].to(self.device))
            self.optimizers["opacities"].load_state_dict(data["optimizer"])
        self.colors = None if data["colors"] is None else data["colors"].to(self.device)
        self.generator.set_state(data["generator"])
        self.history = list(data["history"])
