"""Densification with gsplat DefaultStrategy semantics: clone, split, prune, opacity reset.

A config dataclass, a running state kept apart, and two hooks the training loop calls around
`loss.backward()` (gsplat's strategy/base.py shape). Every edit of the parameter set also edits
the Adam moments, so new Gaussians start with zero momentum and removed ones leave none behind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

Params = dict[str, torch.nn.Parameter]
Optimizers = dict[str, torch.optim.Optimizer]


@dataclass
class DensifyConfig:
    """gsplat 1.5.3 DefaultStrategy defaults, in steps of a 30k-step run (see `scaled`)."""

    prune_opa: float = 0.005
    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01  # x scene_scale: clone at or below, split above
    prune_scale3d: float = 0.1  # x scene_scale, once the first opacity reset has happened
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3_000
    refine_every: int = 100
    max_gaussians: int = 2_000_000  # a budget: growth stops here (CPU memory)
    # > 0: the budget follows the object, this many Gaussians per pixel it covers in the mean training
    # view, capped by max_gaussians: a stone filling twice the image needs about twice the Gaussians.
    per_object_pixel: float = 0.0
    # > 0: growth is paced, the budget opening linearly until this fraction of the refine window has passed.
    # Unpaced, a textured real scene spends the whole budget in its first refines, on coarse early views.
    budget_ramp: float = 0.0

    def budget_at(self, step: int, budget: int) -> int:
        """How many Gaussians growth may reach by `step`."""
        if self.budget_ramp <= 0:
            return budget
        ramp = self.budget_ramp * max(1, self.refine_stop_iter - self.refine_start_iter)
        return round(budget * min(1.0, max(0, step - self.refine_start_iter) / ramp))

    def budget_for(self, object_pixels: float | None) -> int:
        """The Gaussian budget for an object covering `object_pixels` per view (None: unknown, no masks)."""
        if self.per_object_pixel <= 0 or not object_pixels:
            return self.max_gaussians
        return max(1, min(self.max_gaussians, round(self.per_object_pixel * object_pixels)))

    def scaled(self, total_steps: int) -> "DensifyConfig":
        """The same proportions of a run `total_steps` long."""
        f = total_steps / 30_000
        return DensifyConfig(
            prune_opa=self.prune_opa,
            grow_grad2d=self.grow_grad2d,
            grow_scale3d=self.grow_scale3d,
            prune_scale3d=self.prune_scale3d,
            refine_start_iter=max(1, round(self.refine_start_iter * f)),
            refine_stop_iter=max(1, round(self.refine_stop_iter * f)),
            reset_every=max(1, round(self.reset_every * f)),
            refine_every=max(1, round(self.refine_every * f)),
            max_gaussians=self.max_gaussians,
            per_object_pixel=self.per_object_pixel,
            budget_ramp=self.budget_ramp,
        )


@dataclass
class DensifyState:
    grad2d: torch.Tensor | None = None  # [N] summed screen-space gradient norms
    count: torch.Tensor | None = None  # [N] how many views saw each Gaussian
    history: list[dict] = field(default_factory=list)

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count, "history": list(self.history)}

    @staticmethod
    def from_state_dict(data: dict) -> "DensifyState":
        return DensifyState(data["grad2d"], data["count"], list(data["history"]))


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N,4] wxyz -> [N,3,3]."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def update_params(
    params: Params,
    optimizers: Optimizers,
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
) -> None:
    """Replace every parameter by param_fn(name, p) and every Adam moment by state_fn(key, v)."""
    for name in list(params):
        old = params[name]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        optimizer = optimizers[name]
        state = optimizer.state.pop(old, {})
        for key, value in list(state.items()):
            if key != "step" and torch.is_tensor(value) and value.dim() > 0:
                state[key] = state_fn(key, value)
        optimizer.param_groups[0]["params"] = [new]
        if state:
            optimizer.state[new] = state
        params[name] = new


def duplicate(params: Params, optimizers: Optimizers, mask: torch.Tensor) -> None:
    """Clone the selected Gaussians (small ones under-reconstructing a region)."""
    ids = torch.where(mask)[0]
    update_params(
        params,
        optimizers,
        lambda _, p: torch.cat([p, p[ids]]),
        lambda _, v: torch.cat([v, torch.zeros_like(v[ids])]),
    )


def split(params: Params, optimizers: Optimizers, mask: torch.Tensor, generator: torch.Generator) -> None:
    """Replace each selected Gaussian by two samples drawn from it, scaled down by 1.6."""
    sel = torch.where(mask)[0]
    rest = torch.where(~mask)[0]
    scales = torch.exp(params["scales"][sel].detach())  # [S, 3]
    rotmats = quat_to_rotmat(params["quats"][sel].detach())  # [S, 3, 3]
    noise = torch.randn(2, len(sel), 3, generator=generator, device=generator.device).to(scales.device)  # [2, S, 3]
    offsets = torch.einsum("nij,bnj->bni", rotmats, scales[None] * noise)  # [2, S, 3]

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            new = (p[sel][None] + offsets).reshape(-1, 3)
        elif name == "scales":
            new = torch.log(scales / 1.6).repeat(2, 1)
        else:
            new = p[sel].repeat(2, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], new])

    def state_fn(_: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v[rest], torch.zeros((2 * len(sel), *v.shape[1:]), dtype=v.dtype, device=v.device)])

    update_params(params, optimizers, param_fn, state_fn)


def remove(params: Params, optimizers: Optimizers, mask: torch.Tensor) -> None:
    keep = torch.where(~mask)[0]
    update_params(params, optimizers, lambda _, p: p[keep], lambda _, v: v[keep])


def reset_opacity(params: Params, optimizers: Optimizers, value: float) -> None:
    """Clamp every opacity to at most `value` and forget the opacity moments."""
    ceiling = math.log(value / (1 - value))
    opacities = params["opacities"]
    optimizer = optimizers["opacities"]
    new = torch.nn.Parameter(opacities.detach().clamp_max(ceiling), requires_grad=opacities.requires_grad)
    state = optimizer.state.pop(opacities, {})
    for key, v in list(state.items()):
        if key != "step" and torch.is_tensor(v) and v.dim() > 0:
            state[key] = torch.zeros_like(v)
    optimizer.param_groups[0]["params"] = [new]
    if state:
        optimizer.state[new] = state
    params["opacities"] = new


class DefaultStrategy:
    """Hooks: call step_pre_backward before loss.backward() and step_post_backward after it."""

    def __init__(self, cfg: DensifyConfig, scene_scale: float, seed: int = 0):
        self.cfg = cfg
        self.scene_scale = scene_scale
        self.state = DensifyState()
        self.generator = torch.Generator().manual_seed(seed)

    def step_pre_backward(self, info: dict) -> None:
        info["means2d"].retain_grad()

    def step_post_backward(self, params: Params, optimizers: Optimizers, step: int, info: dict) -> None:
        """info: means2d [C,M,2] (M >= N: the first N are the surface), radii [C,M], width, height."""
        cfg = self.cfg
        if step >= cfg.refine_stop_iter:
            return
        self._accumulate(len(params["means"]), info)
        if step > cfg.refine_start_iter and step % cfg.refine_every == 0:
            before = len(params["means"])
            cloned, splitted = self._grow(params, optimizers, step)
            pruned = self._prune(params, optimizers, step)
            self.state.history.append(
                {"step": step, "before": before, "cloned": cloned, "split": splitted, "pruned": pruned}
            )
            self.state.grad2d = self.state.count = None
        if step % cfg.reset_every == 0 and step > 0:
            reset_opacity(params, optimizers, 2 * cfg.prune_opa)

    def _accumulate(self, n: int, info: dict) -> None:
        grad = info["means2d"].grad
        if grad is None:
            return
        grads = grad[:, :n].clone()  # [C, N, 2]
        grads[..., 0] *= info["width"] / 2.0 * grads.shape[0]
        grads[..., 1] *= info["height"] / 2.0 * grads.shape[0]
        if self.state.grad2d is None:
            self.state.grad2d = torch.zeros(n, device=grad.device)
            self.state.count = torch.zeros(n, device=grad.device)
        visible = info["radii"][:, :n] > 0  # [C, N]
        ids = torch.where(visible)[1]
        self.state.grad2d.index_add_(0, ids, grads[visible].norm(dim=-1))
        self.state.count.index_add_(0, ids, torch.ones_like(ids, dtype=torch.float32))

    def _grow(self, params: Params, optimizers: Optimizers, step: int) -> tuple[int, int]:
        if self.state.grad2d is None:
            return 0, 0
        cfg = self.cfg
        grads = self.state.grad2d / self.state.count.clamp_min(1)  # [N]
        high = grads > cfg.grow_grad2d
        small = torch.exp(params["scales"].detach()).max(dim=-1).values <= cfg.grow_scale3d * self.scene_scale
        room = cfg.budget_at(step, cfg.max_gaussians) - len(params["means"])
        if int(high.sum()) > room:  # over budget: grow only the largest gradients that still fit
            if room <= 0:
                return 0, 0
            high &= grads >= torch.topk(grads[high], room).values.min()
        is_dupli = high & small
        is_split = high & ~small
        if is_dupli.any():
            duplicate(params, optimizers, is_dupli)
        clones = torch.zeros(int(is_dupli.sum()), dtype=torch.bool, device=is_split.device)
        is_split = torch.cat([is_split, clones])
        if is_split.any():
            split(params, optimizers, is_split, self.generator)
        return int(is_dupli.sum()), int(is_split.sum())

    def _prune(self, params: Params, optimizers: Optimizers, step: int) -> int:
        cfg = self.cfg
        is_prune = torch.sigmoid(params["opacities"].detach()) < cfg.prune_opa
        if step > cfg.reset_every:
            too_big = torch.exp(params["scales"].detach()).max(dim=-1).values > cfg.prune_scale3d * self.scene_scale
            is_prune |= too_big
        if is_prune.all():  # never leave an empty model; keep the most opaque one
            is_prune[torch.argmax(params["opacities"].detach())] = False
        if is_prune.any():
            remove(params, optimizers, is_prune)
        return int(is_prune.sum())
