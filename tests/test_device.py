"""The trainer's device option, checked without a GPU: `meta` stands in for a device other than the CPU."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from test_trainer import TINY, write_sphere_scan

from station.errors import BadInputError
from station.ngs.dataset import load_scene
from station.ngs.trainer import Trainer, training_device


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    write_sphere_scan(root)
    return load_scene(root)


def test_auto_is_the_cpu_without_cuda_and_bad_names_are_refused():
    assert training_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert training_device("cpu") == torch.device("cpu")
    with pytest.raises(BadInputError, match="not a torch device"):
        training_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(BadInputError, match="sees no CUDA device"):
            training_device("cuda")


def test_a_trainer_puts_its_model_optimisers_views_and_cameras_on_the_configured_device(scene, tmp_path):
    trainer = Trainer(scene, replace(TINY, device="meta"), tmp_path)
    meta = torch.device("meta")
    assert trainer.device == meta
    assert all(p.device == meta for p in trainer.model.params.values())
    assert all(p.device == meta for opt in trainer.optimizers.values() for g in opt.param_groups for p in g["params"])
    views = trainer.scene.train + trainer.scene.test
    assert all(t.device == meta for v in views for t in (v.image, v.mask, v.viewmat, v.K))
    assert all(t.device == meta for cam in trainer.cameras for t in (cam.viewmat, cam.K))
    assert all(v.image.device == torch.device("cpu") for v in scene.train)  # the caller's scene is left alone


def test_no_training_tensor_is_created_on_an_unnamed_device(scene, tmp_path):
    """With torch's default device `meta`, any tensor made without naming the trainer's device lands on meta
    and the first op mixing it with a CPU tensor (or reading it) fails. A run through the infill build,
    the freeze, densification (splits included), held-out SOS and a resume must not meet one: the code that
    makes a tensor names its device, so the trainer needs no device context around the losses or the strategy."""
    cfg = replace(TINY, device="cpu", steps=24, checkpoint_every=16, eval_every=12)
    torch.set_default_device("meta")
    try:
        trainer = Trainer(scene, cfg, tmp_path)
        for step in range(20):
            trainer.train_step(step)
            trainer.step = step + 1
            if trainer.step % cfg.checkpoint_every == 0:
                trainer.save_checkpoint()
        resumed = Trainer(scene, cfg, tmp_path)
        report = resumed.run()
    finally:
        torch.set_default_device("cpu")
    assert any(refine["split"] for refine in trainer.strategy.state.history)
    assert trainer.ngs.infill is not None and len(trainer.ngs.infill) > 0
    assert report.resumed_from == 16 and report.steps == cfg.steps and report.device == "cpu"
    assert [e["sos"] is not None for e in resumed.evals] == [True]
    assert all(p.device.type == "cpu" for p in resumed.model.params.values())

