"""Compile training's numba kernels (rasteriser, SSIM) before training needs them, in a process of its own.

numba compiles a kernel on its first call and keeps it in its on-disk cache. On a fresh install that first
call is training's first step, which then spends the best part of a minute compiling on one core before
anything trains. `start_kernel_warmup` runs every kernel once on a tiny scene in a spawned process, so the
compile overlaps work that leaves a core free (a scan waits on the turntable and the camera; develop and
posing wait on files). Training then loads the kernels from the cache. With a warm cache it costs the
spawned process a few seconds of loading.
"""

from __future__ import annotations

import multiprocessing
import os
from multiprocessing.process import BaseProcess

import torch

from station.ngs.losses import ssim
from station.ngs.raster import median_depth, rasterization, seen_in_front


def exercise_kernels() -> None:
    """Every training kernel once, with the argument types training passes."""
    exercise_raster_kernels()
    exercise_ssim_kernels()


def exercise_raster_kernels() -> None:
    """The rasteriser's kernels: float32, SH coefficients, an extra channel (NGS's noise flag), a backward pass,
    and the infill's depth and depth-pruning queries."""
    generator = torch.Generator().manual_seed(0)
    n, size = 64, 32
    means = ((torch.rand(n, 3, generator=generator) - 0.5) * 0.5).requires_grad_()
    quats = torch.randn(n, 4, generator=generator).requires_grad_()
    scales = torch.full((n, 3), 0.05).requires_grad_()
    opacities = torch.full((n,), 0.5).requires_grad_()
    coeffs = (0.1 * torch.randn(n, 4, 3, generator=generator)).requires_grad_()
    viewmat = torch.eye(4)
    viewmat[2, 3] = 2.0
    K = torch.tensor([[40.0, 0.0, size / 2], [0.0, 40.0, size / 2], [0.0, 0.0, 1.0]])
    for extra in (None, torch.ones(n, 1)):
        colors, alphas, _ = rasterization(means, quats, scales, opacities, coeffs, viewmat[None], K[None], size, size,
                                          sh_degree=1, extra=extra)
        (colors.sum() + alphas.sum()).backward()
    surface = [t.detach() for t in (means, quats, scales, opacities)]
    median_depth(*surface, viewmat, K, size, size, alpha_level=torch.full((size, size), 0.5))
    seen_in_front(*surface, viewmat, K, size, size, torch.full((size, size), 2.0))


def exercise_ssim_kernels() -> None:
    """The SSIM loss's kernels, forward and backward, on float32 images (a module of their own: a test warm-up
    compiles them beside the rasteriser's)."""
    image = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(0)).requires_grad_()
    ssim(image, torch.zeros(32, 32, 3)).backward()


def _exercise_kernels_niced() -> None:
    """At low priority: the scan beside it keeps the cores it uses (at normal priority the demo's scan took
    45% longer), and the compile takes what they leave idle."""
    os.nice(10)
    exercise_kernels()


def start_kernel_warmup() -> BaseProcess:
    """`exercise_kernels` in a spawned daemon process at low priority (it ends with this one); returns it."""
    process = multiprocessing.get_context("spawn").Process(target=_exercise_kernels_niced, name="kernel-warmup",
                                                           daemon=True)
    process.start()
    return process
