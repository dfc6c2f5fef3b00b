"""A batch stage process keeps to its share of the cores once numba's thread pool has started."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# Run as a script, outside pytest's one-thread worker environment, in a child of a forkserver that
# has made the local executor's preloads, as a stage process is.
STAGE_LIKE = textwrap.dedent("""
    import multiprocessing


    def pools_after_a_parallel_kernel(result):
        import numba
        import numpy as np
        import torch

        from station.batch.stage_run import limit_threads
        from station.ngs import _kernels

        limit_threads(1)
        one = np.ones(1, np.float32)
        _kernels.bin_gaussians(np.full((1, 2), 4.0, np.float32), np.array([[1.0, 0.0, 1.0]], np.float32), one,
                               np.ones(1, np.int32), one, 8, 8)
        result.send((torch.get_num_threads(), numba.get_num_threads()))


    if __name__ == "__main__":
        from station.batch.executors import PRELOAD

        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(PRELOAD)
        receive, send = context.Pipe(duplex=False)
        process = context.Process(target=pools_after_a_parallel_kernel, args=(send,))
        process.start()
        send.close()
        print(receive.recv())
        process.join()
""")


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: a reset to all cores is a reset to one")
@pytest.mark.timeout(240)
def test_a_one_thread_stage_keeps_torch_and_numba_at_one_thread_after_numba_starts_its_pool(tmp_path: Path):
    script = tmp_path / "stage_like.py"
    script.write_text(STAGE_LIKE)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS")}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=200, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "(1, 1)"
