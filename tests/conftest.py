"""Test-wide set-up that must happen before any test module imports torch or numba."""

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see station/__init__.py
# Error lines name temp paths, longer under xdist (popen-gwN/): wide enough that rich never breaks a name.
os.environ.setdefault("COLUMNS", "240")

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    # One xdist worker per core: each worker, and every stage process it starts, keeps to one thread,
    # or the torch and numba pools of two workers oversubscribe the cores and crawl.
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[_name] = "1"
    # numba rewrites a function's whole cache index on each save, so two processes saving different
    # signatures of one kernel at once can pair an index entry with the other's code: a cache per worker.
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "numba" / _WORKER))


@pytest.fixture(scope="session")
def tiny_shot(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """tiny_shot(stone): a finished 2 x 8 scan of `stone` at 160x120, shot once per worker for every
    batch module that asks for it. It is shared: copy it (batch_support.copy_scans) before changing it.

    The first shot is also run through every stage once, in a process of its own, so numba's cache for this
    worker holds the stages' kernels before a batch starts: otherwise each stage process the batch starts
    before the first has saved them compiles them again, and on a fresh clone that doubled the batch tests."""
    from batch_support import copy_scans, shoot

    shots: dict[str, Path] = {}

    def shot(stone: str) -> Path:
        if stone not in shots:
            shots[stone] = shoot(tmp_path_factory.mktemp("tiny-shot") / f"stone{stone}", stone)
            if len(shots) == 1:
                warm = copy_scans([shots[stone]], tmp_path_factory.mktemp("kernel-warm-up"))[0]
                done = subprocess.run([sys.executable, "-m", "station", "run", str(warm), "--preset", "tiny"],
                                      capture_output=True, text=True, timeout=600)
                assert done.returncode in (0, 1), done.stderr[-3000:]  # 1: the tiny model's gate failed
        return shots[stone]

    return shot
