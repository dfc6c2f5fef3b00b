"""Worker processes of a per-frame map (workers.py) end with the process that started them."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.no_kernels

PARENT = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from station.process.workers import map_in_workers

    def job(i):
        Path(sys.argv[1], str(os.getpid())).touch()
        time.sleep(60)

    def keep(context):
        pass

    if __name__ == "__main__":
        map_in_workers(job, range(4), None, keep, workers=2)
""")


def _alive(pid: int) -> bool:
    """Running, not gone or a zombie waiting for init to reap it."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_workers_leave_when_their_parent_is_killed_mid_job(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    marks = tmp_path / "workers"
    marks.mkdir()
    parent = subprocess.Popen([sys.executable, str(script), str(marks)], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 120
    while len(list(marks.iterdir())) < 2 and time.monotonic() < deadline and parent.poll() is None:
        time.sleep(0.2)
    workers = [int(p.name) for p in marks.iterdir()]
    assert len(workers) == 2, parent.communicate(timeout=5)[0] if parent.poll() is not None else "workers never started"
    parent.send_signal(signal.SIGKILL)
    deadline = time.monotonic() + 20
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers)
    parent.communicate(timeout=20)  # and nothing holds the parent's stdout open: a reader sees its end
