"""Compile every stage's numba kernels into one cache while the tests that call none run (see conftest.py).

Two processes compile at once, each in modules of its own, so no kernel's cache index is written by
both: the rasteriser's kernels (station.ngs.warmup) in one; in the other a tiny scan's process stage,
then the SSIM kernels and the export's opacity field. Between them they cover what a tiny scan's train
and export call: running those too compiled nothing more, and cost the warm-up about 17 s.

Run as `python tests/warm_kernels.py WORKDIR` with NUMBA_CACHE_DIR set; exits non-zero if a stage failed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from station.export.opacity_field import opacity_field
from station.export.splat_model import SplatModel
from station.ngs.warmup import exercise_ssim_kernels

STATION = [sys.executable, "-m", "station"]


def exercise_opacity_field() -> None:
    """The export mesher's kernel, on two Gaussians with the argument types export passes."""
    model = SplatModel(means=np.zeros((2, 3)), scales_log=np.full((2, 3), -3.0), quats=np.tile([1.0, 0, 0, 0], (2, 1)),
                       opacity_logit=np.zeros(2), sh_dc=np.zeros((2, 3)), sh_rest=np.zeros((2, 0, 3)))
    opacity_field(model, np.full(3, -0.1), 0.05, (4, 4, 4))


def main(workdir: Path) -> int:
    raster = subprocess.Popen([sys.executable, "-c",
                               "from station.ngs.warmup import exercise_raster_kernels; exercise_raster_kernels()"])
    sys.path.insert(0, str(Path(__file__).parent))
    from batch_support import shoot

    scan = shoot(workdir / "scan", "1")
    process = subprocess.run([*STATION, "process", str(scan)], capture_output=True, text=True)
    exercise_ssim_kernels()
    exercise_opacity_field()
    rastered = raster.wait()
    if process.returncode != 0 or rastered != 0:
        sys.stderr.write(process.stderr[-3000:])
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
