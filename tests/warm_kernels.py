"""Compile every stage's numba kernels into one cache before the test workers start (see conftest.py).

Two processes compile at once, each in modules of its own, so no kernel's cache index is written by
both: training's kernels (station.ngs.warmup) and a tiny scan's process stage. Then that scan runs
through train, which loads its kernels, and export, which compiles its own.

Run as `python tests/warm_kernels.py WORKDIR` with NUMBA_CACHE_DIR set; exits non-zero if a stage failed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

STATION = [sys.executable, "-m", "station"]


def main(workdir: Path) -> int:
    training = subprocess.Popen([sys.executable, "-c",
                                 "from station.ngs.warmup import exercise_kernels; exercise_kernels()"])
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
    sys.exit(main(Path(sys.argv[1])))
