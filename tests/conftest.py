"""Test-wide set-up that must happen before any test module imports torch or numba."""

import fcntl
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see station/__init__.py
# Error lines name temp paths, longer under xdist (popen-gwN/): wide enough that rich never breaks a name.
os.environ.setdefault("COLUMNS", "240")

_ROOT = Path(__file__).resolve().parents[1]
_WARM_CACHE = _ROOT / ".pytest_cache" / "numba" / "warm"  # every stage's kernels, compiled once per source change
_STAMP = "sources.sha256"
_WARM_ENDED = _WARM_CACHE.parent / "warm.ended"  # written when the controller's compile ends, however it ends
_WARMING_ENV = "STATION_TEST_WARMING"  # set by the controller while it compiles: the workers must wait for it
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
else:
    os.environ.setdefault("NUMBA_CACHE_DIR", str(_WARM_CACHE))
_warm_cache_adopted = False


def _adopt_warm_cache() -> None:
    """Before this process's first kernel: wait for the controller's compile, if one is under way, then start
    a worker's own cache from the warm one. Without it each worker compiled every kernel again, inside
    whichever test came first and against that test's timeout."""
    global _warm_cache_adopted
    if _warm_cache_adopted:
        return
    deadline = time.monotonic() + 960  # the compile's own limit is 900 s
    while _WARMING_ENV in os.environ and not _WARM_ENDED.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    warm_stamp, own_stamp = _WARM_CACHE / _STAMP, Path(os.environ["NUMBA_CACHE_DIR"]) / _STAMP
    if _WORKER and warm_stamp.is_file() and (not own_stamp.is_file()
                                             or own_stamp.read_bytes() != warm_stamp.read_bytes()):
        shutil.copytree(_WARM_CACHE, own_stamp.parent, dirs_exist_ok=True)
    _warm_cache_adopted = True


if _WORKER and _WARMING_ENV not in os.environ:
    _adopt_warm_cache()


def _sources_digest() -> str:
    """What numba's cached kernels depend on: the code that defines or calls them, and numba itself."""
    import importlib.metadata

    digest = hashlib.sha256(importlib.metadata.version("numba").encode())
    for path in sorted([*(_ROOT / "station").rglob("*.py"), *(_ROOT / "sim").rglob("*.py")]):
        digest.update(path.relative_to(_ROOT).as_posix().encode() + path.read_bytes())
    return digest.hexdigest()


class _WarmUp:
    """The controller's compile of the warm cache, in a process group of its own beside the first tests."""

    def __init__(self, digest: str) -> None:
        self.digest, self.started, self.failure, self.seconds = digest, time.monotonic(), None, None
        _WARM_ENDED.unlink(missing_ok=True)
        (_WARM_CACHE / _STAMP).unlink(missing_ok=True)  # the cache is being rewritten: no worker may adopt it
        _WARM_CACHE.mkdir(parents=True, exist_ok=True)
        self.workdir = tempfile.mkdtemp(prefix="station-warm-")
        self.process = subprocess.Popen([sys.executable, str(_ROOT / "tests" / "warm_kernels.py"), self.workdir],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                        start_new_session=True)
        os.environ[_WARMING_ENV] = "1"  # inherited by the workers, which start after this
        self.thread = threading.Thread(target=self._wait, name="kernel-warm-up", daemon=True)
        self.thread.start()

    def _wait(self) -> None:
        try:
            _, stderr = self.process.communicate(timeout=900)
            if self.process.returncode == 0:
                (_WARM_CACHE / _STAMP).write_text(self.digest)
            elif self.process.returncode > 0:
                self.failure = stderr[-2000:]
            else:
                self.failure = f"it was stopped by signal {-self.process.returncode}"
        except subprocess.TimeoutExpired:
            self._kill()
            self.process.communicate()
            self.failure = "it ran past 900 s"
        finally:
            self.seconds = time.monotonic() - self.started
            shutil.rmtree(self.workdir, ignore_errors=True)
            _WARM_ENDED.touch()

    def _kill(self) -> None:
        """The compile and the stage processes it started."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def stop(self) -> None:
        """End the compile: the tests left needed none of it."""
        self._kill()
        self.thread.join()


_warm_up: _WarmUp | None = None


def pytest_configure(config: pytest.Config) -> None:
    """In the controller, before any worker starts: if the sources changed, start compiling every stage's
    kernels into the warm cache. The tests marked `no_kernels` run meanwhile (they are ordered first); every
    other test waits for it (pytest_runtest_setup)."""
    global _warm_up
    if _WORKER or os.environ["NUMBA_CACHE_DIR"] != str(_WARM_CACHE) or config.option.collectonly:
        return
    digest = _sources_digest()
    stamp = _WARM_CACHE / _STAMP
    if stamp.is_file() and stamp.read_text() == digest:
        return
    print("compiling the stages' numba kernels once for every test worker, beside the tests that need none",
          file=sys.stderr, flush=True)
    _warm_up = _WarmUp(digest)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The modules marked `no_kernels` first, those with the most tests first (as xdist's own reorder would):
    they run while the kernels compile. The rest keep their order."""
    tests_per_module = Counter(item.nodeid.split("::")[0] for item in items)
    items.sort(key=lambda item: (0, -tests_per_module[item.nodeid.split("::")[0]])
               if item.get_closest_marker("no_kernels") else (1, 0))


_no_kernels_test_started = 0.0


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    global _no_kernels_test_started
    if item.get_closest_marker("no_kernels") is None:
        _adopt_warm_cache()
    else:
        _no_kernels_test_started = time.time()


def pytest_runtest_teardown(item: pytest.Item) -> None:
    """A `no_kernels` test that compiled a kernel (here or in a process it started, into this worker's cache) did
    it beside the warm-up and against its own timeout: its marker is wrong."""
    if _WORKER and not _warm_cache_adopted and item.get_closest_marker("no_kernels"):
        compiled = sorted(path.stem for path in Path(os.environ["NUMBA_CACHE_DIR"]).rglob("*.nbi")
                          if path.stat().st_mtime >= _no_kernels_test_started)
        if compiled:
            pytest.fail(f"marked no_kernels, but it compiled {', '.join(compiled)}", pytrace=False)


def pytest_terminal_summary(terminalreporter) -> None:
    if _warm_up is None or _warm_up.seconds is None:
        return
    if _warm_up.failure is None:
        terminalreporter.write_line(f"numba kernels compiled in {_warm_up.seconds:.0f} s, beside the first tests")
    else:  # the tests that ran these stages showed why; they compiled as they went
        terminalreporter.write_line(f"kernel warm-up failed; each worker compiled on demand:\n{_warm_up.failure}")


def pytest_unconfigure(config: pytest.Config) -> None:
    if _warm_up is not None and _warm_up.seconds is None:
        _warm_up.stop()


@pytest.fixture(scope="session")
def tiny_shot(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """tiny_shot(stone): a finished 2 x 8 scan of `stone` at 160x120, shot once per test run for every batch
    module that asks for it, by whichever worker asks first (the others wait for it). It is shared: copy it
    (batch_support.copy_scans) before changing it.

    The stages' kernels are in this worker's numba cache already (pytest_runtest_setup): otherwise each stage
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
