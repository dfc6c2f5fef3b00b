"""Fault injection for tests/test_batch_faults.py, in every Python process it starts with this folder on
PYTHONPATH (the batch CLI, its forkserver, each stage process): with STATION_TEST_INJECT_NAN="STEP:SCAN"
set, the training run in scan folder SCAN gets a NaN in one mean at STEP, so the trainer's own
check_finite guard is what stops it. The production code carries no hook."""

import os

_SPEC = os.environ.get("STATION_TEST_INJECT_NAN", "")
if _SPEC:
    from pathlib import Path

    import torch

    from station.ngs.trainer import Trainer

    _STEP, _, _SCAN = _SPEC.partition(":")
    _train_step = Trainer.train_step

    def _poisoned(self: Trainer, step: int) -> dict[str, float]:
        if step == int(_STEP) and self.model_dir.resolve().parent == Path(_SCAN).resolve():
            with torch.no_grad():
                self.model.params["means"][0, 0] = float("nan")
        return _train_step(self, step)

    Trainer.train_step = _poisoned
