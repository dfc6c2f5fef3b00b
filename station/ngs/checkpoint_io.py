"""Model files from an untrusted scan folder: checkpoint.pt, surface.pt and infill.pt, loaded and checked.

`torch.load` on a truncated file raises its own RuntimeError, on an empty one EOFError (which the
CLI framework prints as a bare "Aborted!"), and on a well-formed file of the wrong layout the
KeyError surfaces deep in training. Every model file is therefore read here: weights only (no
pickled code), any failure a CheckpointError naming the file, and the layout checked before use.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from station.errors import CheckpointError, InputTooLargeError
from station.ngs.gaussians import PARAM_NAMES

MAX_MODEL_BYTES = 8 * 1024**3
TRAINING_KEYS = {"config": dict, "step": int, "seconds": float, "model": dict, "optimizers": dict, "strategy": dict,
                 "strategy_generator": torch.Tensor, "generator": torch.Tensor, "losses": list, "evals": list,
                 "extensions": list, "resolution": dict}


def load_weights(path: Path) -> dict[str, Any]:
    """The dict a model file holds, read with weights_only=True; anything unreadable is a CheckpointError."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, None, "missing")
    size = path.stat().st_size
    if size == 0:
        raise CheckpointError(path, None, "empty file (0 bytes): delete it and run the stage again")
    if size > MAX_MODEL_BYTES:
        raise InputTooLargeError(path, None, f"{size} bytes exceeds the {MAX_MODEL_BYTES}-byte limit for a model file")
    try:
        data = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises RuntimeError, EOFError, UnpicklingError, KeyError... on garbage
        raise CheckpointError(path, None, f"truncated or not a torch model file ({type(exc).__name__}): "
                                          "delete it and run the stage again") from exc
    if not isinstance(data, dict):
        raise CheckpointError(path, None, f"holds a {type(data).__name__}, expected a dict")
    return data


def _tensor(value: Any, path: Path, field: str, shape: tuple[int | None, ...], floating: bool = True) -> torch.Tensor:
    """`value` must be a finite tensor of `shape` (None: any length)."""
    if not isinstance(value, torch.Tensor):
        raise CheckpointError(path, field, f"must be a tensor, got {type(value).__name__}")
    if value.ndim != len(shape) or any(want is not None and got != want for got, want in zip(value.shape, shape)):
        raise CheckpointError(path, field, f"has shape {tuple(value.shape)}, expected {shape}")
    if floating and (not value.is_floating_point() or not torch.isfinite(value).all()):
        raise CheckpointError(path, field, "must hold finite floating-point values")
    return value


def check_gaussian_params(params: Any, path: Path, field: str) -> None:
    """gsplat's splat layout: means [N,3], scales [N,3], quats [N,4], opacities [N], sh0 [N,1,3], shN [N,K,3]."""
    if not isinstance(params, dict):
        raise CheckpointError(path, field, "must be a dict of tensors")
    means = _tensor(params.get("means"), path, f"{field}.means", (None, 3))
    n = means.shape[0]
    if n < 1:
        raise CheckpointError(path, f"{field}.means", "holds no Gaussians")
    for name, shape in (("scales", (n, 3)), ("quats", (n, 4)), ("opacities", (n,)), ("sh0", (n, 1, 3)),
                        ("shN", (n, None, 3))):
        _tensor(params.get(name), path, f"{field}.{name}", shape)
    bases = params["shN"].shape[1] + 1
    if math.isqrt(bases) ** 2 != bases or bases > 25:
        raise CheckpointError(path, f"{field}.shN", f"{bases} SH bases is not (degree+1)^2 for degree 0..4")
    extra = set(params) - set(PARAM_NAMES)
    if extra:
        raise CheckpointError(path, field, f"unknown parameters {sorted(extra)}")


def load_surface_file(path: Path) -> dict[str, Any]:
    """model/surface.pt: {"params": splat layout, "downscale": int >= 1, ...}."""
    data = load_weights(path)
    check_gaussian_params(data.get("params"), path, "params")
    downscale = data.get("downscale")
    if not isinstance(downscale, int) or isinstance(downscale, bool) or not 1 <= downscale <= 64:
        raise CheckpointError(path, "downscale", f"must be a whole number 1..64, got {downscale!r}")
    return data


def load_infill_file(path: Path) -> dict[str, torch.Tensor]:
    """model/infill.pt: means [M,3], scales [M], levels [M] (integer grid resolutions)."""
    data = load_weights(path)
    means = _tensor(data.get("means"), path, "means", (None, 3))
    m = means.shape[0]
    _tensor(data.get("scales"), path, "scales", (m,))
    levels = _tensor(data.get("levels"), path, "levels", (m,), floating=False)
    if levels.is_floating_point() or levels.dtype == torch.bool:
        raise CheckpointError(path, "levels", f"must hold integers, got {levels.dtype}")
    return data


def load_training_checkpoint(path: Path) -> dict[str, Any]:
    """model/checkpoint.pt as the trainer writes it, its layout checked before anything is restored."""
    data = load_weights(path)
    for key, kind in TRAINING_KEYS.items():
        value = data.get(key)
        if not isinstance(value, kind) or isinstance(value, bool) or (kind is float and not math.isfinite(value)):
            raise CheckpointError(path, key, f"must be a {kind.__name__}, got {type(value).__name__}")
    if data["step"] < 0:
        raise CheckpointError(path, "step", f"must not be negative, got {data['step']}")
    check_gaussian_params(data["model"], path, "model")
    generator_size = torch.Generator().get_state().shape
    for key in ("generator", "strategy_generator"):
        if data[key].dtype != torch.uint8 or data[key].shape != generator_size:
            raise CheckpointError(path, key, "is not a torch.Generator state")
    for name, opt in data["optimizers"].items():
        if not isinstance(opt, dict) or not isinstance(opt.get("state"), dict) or not isinstance(opt.get("param_groups"), list):
            raise CheckpointError(path, f"optimizers.{name}", "is not an optimizer state dict")
    strategy = data["strategy"]
    n = data["model"]["means"].shape[0]
    for key in ("grad2d", "count"):  # None between densification rounds
        if strategy.get(key) is not None:
            _tensor(strategy[key], path, f"strategy.{key}", (n,), floating=False)
    for field, value in (("strategy.history", strategy.get("history")), ("resolution.checks", data["resolution"].get("checks"))):
        if not isinstance(value, list):
            raise CheckpointError(path, field, f"must be a list, got {type(value).__name__}")
    if data.get("ngs") is not None and not isinstance(data["ngs"], dict):
        raise CheckpointError(path, "ngs", "must be a dict or None")
    return data
