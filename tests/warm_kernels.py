"""Compile every stage's numba kernels into one cache before the test workers start (see conftest.py).

Two processes compile at once, each in modules of its own, so no kernel's cache index is written by
both: training's kernels (station.ngs.warmup, then the float64 paths the rasteriser's tests check
gradients on) and a tiny scan's process stage. Then that scan runs through train, which loads its
kernels, and export, which compiles its own.

Run as `python tests/warm_kernels.py WORKDIR` with NUMBA_CACHE_DIR set; exits non-zero if a stage failed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

STATION = [sys.executable, "-m", "station"]
RASTER_KERNELS = "--raster-kernels"  # argument: compile the rasteriser's kernels in this process, then exit


def exercise_float64_kernels() -> None:
    """The rasteriser's kernels in float64, as its tests call them: forward and backward with SH colours,
    expected depth and a background, with plain RGB and a background that takes a gradient, then median depth
    (one level and a level a pixel) and the contributor listing. Training never compiles these; without them
    the first float64 test (gradcheck) compiled them all, for over a minute, inside its own timeout."""
    import torch

    from station.ngs.raster import median_depth, pixel_contributors, rasterization

    generator = torch.Generator().manual_seed(0)
    n, size = 16, 16
    surface = [((torch.rand(n, 3, generator=generator) - 0.5) * 0.5).double(),
               torch.randn(n, 4, generator=generator).double(), torch.full((n, 3), 0.05, dtype=torch.float64),
               torch.full((n,), 0.5, dtype=torch.float64)]
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[2, 3] = 2.0
    K = torch.tensor([[20.0, 0.0, size / 2], [0.0, 20.0, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    for colors, sh_degree, mode in ((0.1 * torch.randn(n, 9, 3, generator=generator).double(), 2, "RGB+ED"),
                                    (torch.rand(n, 3, generator=generator).double(), None, "RGB")):
        leaves = [t.clone().requires_grad_() for t in (*surface, colors)]
        background = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64, requires_grad=sh_degree is None)
        image, alpha, _ = rasterization(*leaves, viewmat[None], K[None], size, size, sh_degree=sh_degree,
                                        render_mode=mode, backgrounds=background, backend="cpu")
        (image.sum() + alpha.sum()).backward()
    median_depth(*surface, viewmat, K, size, size, backend="cpu")
    median_depth(*surface, viewmat, K, size, size, alpha_level=torch.full((size, size), 0.5, dtype=torch.float64),
                 backend="cpu")
    pixel_contributors(*surface, viewmat, K, size, size, backend="cpu")


def exercise_raster_kernels() -> None:
    from station.ngs.warmup import exercise_kernels

    exercise_kernels()
    exercise_float64_kernels()


def main(workdir: Path) -> int:
    training = subprocess.Popen([sys.executable, __file__, RASTER_KERNELS])
    sys.path.insert(0, str(Path(__file__).parent))
    from batch_support import shoot

    scan = shoot(workdir / "scan", "1")
    process = subprocess.run([*STATION, "process", str(scan)], capture_output=True, text=True)
    trained = training.wait()
    if process.returncode != 0 or trained != 0:
        sys.stderr.write(process.stderr[-3000:])
        return 1
    run = subprocess.run([*STATION, "run", str(scan), "--preset", "tiny"], capture_output=True, text=True)
    if run.returncode not in (0, 1):  # 1: the tiny model's gate failed, as it mostly does
        sys.stderr.write(run.stderr[-3000:])
        return 1
    return 0


if __name__ == "__main__":
    if sys.argv[1:] == [RASTER_KERNELS]:
        exercise_raster_kernels()
        sys.exit(0)
    sys.exit(main(Path(sys.argv[1])))
