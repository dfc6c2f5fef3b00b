"""Test-wide set-up that must happen before any test module imports torch or numba."""

import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see station/__init__.py
# Error lines name temp paths, longer under xdist (popen-gwN/): wide enough that rich never breaks a name.
os.environ.setdefault("COLUMNS", "240")

_ROOT = Path(__file__).resolve().parents[1]
_WARM_CACHE = _ROOT / ".pytest_cache" / "numba" / "warm"  # every stage's kernels, compiled once before the tests
_STAMP = "sources.sha256"
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    # One xdist worker per core: each worker, and every stage process it starts, keeps to one thread,
    # or the torch and numba pools of two workers oversubscribe the cores and crawl.
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[_name] = "1"
    # numba rewrites a function's whole cache index on each save, so two processes saving different
    # signatures of one kernel at once can pair an index entry with the other's code: a cache per worker.
    # The controller's NUMBA_CACHE_DIR (the warm cache, set below) is inherited: replace it, keep any other.
    if os.environ.get("NUMBA_CACHE_DIR", str(_WARM_CACHE)) == str(_WARM_CACHE):
        os.environ["NUMBA_CACHE_DIR"] = str(_ROOT / ".pytest_cache" / "numba" / _WORKER)
    _warm_stamp, _own_stamp = _WARM_CACHE / _STAMP, Path(os.environ["NUMBA_CACHE_DIR"]) / _STAMP
    if _warm_stamp.is_file() and (not _own_stamp.is_file() or _own_stamp.read_bytes() != _warm_stamp.read_bytes()):
        shutil.copytree(_WARM_CACHE, _own_stamp.parent, dirs_exist_ok=True)  # start from the controller's warm cache
else:
    os.environ.setdefault("NUMBA_CACHE_DIR", str(_WARM_CACHE))


def _sources_digest() -> str:
    """What numba's cached kernels depend on: the code that defines or calls them, and numba itself."""
    import importlib.metadata

    digest = hashlib.sha256(importlib.metadata.version("numba").encode())
    for path in sorted([*(_ROOT / "station").rglob("*.py"), *(_ROOT / "sim").rglob("*.py")]):
        digest.update(path.relative_to(_ROOT).as_posix().encode() + path.read_bytes())
    return digest.hexdigest()


def pytest_configure(config: pytest.Config) -> None:
    """In the controller, before any worker starts: compile every stage's kernels once into the warm cache,
    which each worker copies as its own. Without it each worker compiled them again, inside whichever test
    came first and against that test's timeout."""
    if _WORKER or os.environ["NUMBA_CACHE_DIR"] != str(_WARM_CACHE) or config.option.collectonly:
        return
    digest = _sources_digest()
    stamp = _WARM_CACHE / _STAMP
    if stamp.is_file() and stamp.read_text() == digest:
        return
    _WARM_CACHE.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print("compiling the stages' numba kernels once for every test worker ...", file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory(prefix="station-warm-") as workdir:
        try:
            done = subprocess.run([sys.executable, str(_ROOT / "tests" / "warm_kernels.py"), workdir],
                                  capture_output=True, text=True, timeout=900)
            failure = done.stderr[-2000:] if done.returncode != 0 else None
        except subprocess.TimeoutExpired:
            failure = "it ran past 900 s"
    if failure is not None:  # the tests that run these stages will show why; they compile as they go
        print(f"kernel warm-up failed; each worker compiles on demand:\n{failure}", file=sys.stderr)
        return
    stamp.write_text(digest)
    print(f"... done in {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)


@pytest.fixture(scope="session")
def tiny_shot(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """tiny_shot(stone): a finished 2 x 8 scan of `stone` at 160x120, shot once per test run for every batch
    module that asks for it, by whichever worker asks first (the others wait for it). It is shared: copy it
    (batch_support.copy_scans) before changing it.

    The stages' kernels are in this worker's numba cache already (pytest_configure): otherwise each stage
    process a batch starts before the first has saved them compiles them again."""
    from batch_support import shoot

    base = tmp_path_factory.getbasetemp()
    shots = (base.parent if _WORKER else base) / "tiny-shots"  # the run's own temp root, which its workers share
    shots.mkdir(exist_ok=True)

    def shot(stone: str) -> Path:
        scan, partial = shots / f"stone{stone}", shots / f"stone{stone}.partial"
        with open(shots / f"stone{stone}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not scan.exists():  # shot whole, then renamed: a worker that died mid-shot left only `partial`
                shutil.rmtree(partial, ignore_errors=True)
                shoot(partial, stone).rename(scan)
        return scan

    return shot
