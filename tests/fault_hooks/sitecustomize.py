"""Fault injection for the batch tests, in every Python process they start with this folder on PYTHONPATH
(the batch CLI, its forkserver, each stage process). The production code carries no hook.

- STATION_TEST_INJECT_NAN="STEP:SCAN": the training run in scan folder SCAN gets a NaN in one mean at
  STEP, so the trainer's own check_finite guard is what stops it (test_batch_faults.py).
- STATION_TEST_SLOW_STEP="SECONDS:SCAN": each training step in SCAN sleeps that long first, so a stage is
  still training when its runner's lease runs out, however fast the machine (test_batch_stall.py).
"""

import os

_NAN = os.environ.get("STATION_TEST_INJECT_NAN", "")
_SLOW = os.environ.get("STATION_TEST_SLOW_STEP", "")
if _NAN or _SLOW:
    import time
    from pathlib import Path

    import torch

    from station.ngs.trainer import Trainer

    def _value_and_scan(spec: str):
        value, _, scan = spec.partition(":")
        return value, Path(scan).resolve()

    _train_step = Trainer.train_step
    _nan_step, _nan_scan = _value_and_scan(_NAN) if _NAN else (None, None)
    _slow_seconds, _slow_scan = _value_and_scan(_SLOW) if _SLOW else (None, None)

    def _faulty(self: Trainer, step: int) -> dict[str, float]:
        scan = self.model_dir.resolve().parent
        if _slow_scan == scan:
            time.sleep(float(_slow_seconds))
        if _nan_scan == scan and step == int(_nan_step):
            with torch.no_grad():
                self.model.params["means"][0, 0] = float("nan")
        return _train_step(self, step)

    Trainer.train_step = _faulty
