"""The one stage table as the CLI drives it: containment, the atomic swap, fingerprints, exit codes.

Training and export run for real on the trainer tests' sphere scan (32x32 views), with the `tiny`
preset cut to a few dozen steps so the module stays quick on a busy machine; the stages' own
tests cover what they write.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from station.cli import app
from station.cli_support import exits_on_station_errors
from station.errors import INTERNAL_EXIT_CODE, ScanFolderError
from station.pipeline import (
    STAGES,
    clean_stage,
    perform,
    read_record,
    run_stage,
    spec,
    stage_done,
    write_started,
)
from station.scanfolder import ScanFolder, atomic_write_bytes
from test_trainer import write_sphere_scan

TINY = {"method": "ngs", "preset": "tiny"}


@pytest.fixture(scope="module", autouse=True)
def short_tiny_preset():
    """The `tiny` preset, shortened: what is under test is which checkpoint is resumed, not the model."""
    from station.ngs import presets

    def short() -> presets.TrainConfig:
        return replace(presets.tiny_preset(), steps=40, checkpoint_every=20)

    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(presets.PRESETS, "tiny", short)
        yield


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """The sphere scan trained once through the pipeline (the `station train` path)."""
    root = tmp_path_factory.mktemp("trained") / "sphere"
    write_sphere_scan(root)
    run_stage(root, "train", TINY)
    return root


def copy_of(trained: Path, tmp_path: Path) -> ScanFolder:
    return ScanFolder(shutil.copytree(trained, tmp_path / "sphere", symlinks=True))


# -- one table ------------------------------------------------------------------------------------
def test_the_table_lists_each_stage_once_with_what_it_reads_and_swaps():
    assert [s.name for s in STAGES] == ["process", "train", "export"]
    assert spec("train").reads == ("process",) and spec("export").reads == ("process", "train")
    assert spec("train").folders == ("model",) and spec("export").folders == ("asset",)


def test_a_trained_scan_is_done_for_the_cli_the_batch_and_the_dashboard(trained):
    scan = ScanFolder(trained)
    record = read_record(scan, "train")
    assert record["state"] == "done" and "model/surface.pt" in record["outputs"]
    assert stage_done(scan, "train") and not stage_done(scan, "export")
    assert run_stage(trained, "train", TINY, skip_done=True) is None  # skipped: same key, outputs verify
    assert not any(p.name.startswith(".model.") for p in trained.iterdir())  # no fresh or old folder left


def test_the_train_report_names_the_model_folder_it_was_swapped_into(trained):
    scan = ScanFolder(trained)
    metrics = json.loads((scan.model_dir / "train_metrics.json").read_text())
    for report in (read_record(scan, "train")["summary"], scan.stage_info("train"), metrics["report"]):
        assert report["model_dir"] == str(scan.model_dir)


# -- containment ----------------------------------------------------------------------------------
@pytest.mark.parametrize("folder", ["model", ".model.new", "stages"])
def test_a_symlinked_stage_folder_is_refused_and_nothing_is_written_through_it(trained, tmp_path, folder):
    scan = copy_of(trained, tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "surface.pt").write_bytes(b"someone else's file")
    target = scan.root / folder
    if target.exists():
        shutil.rmtree(target)
    target.symlink_to(outside)
    with pytest.raises(ScanFolderError, match="symbolic link"):
        perform(scan.root, "train", TINY)
    assert [(p.name, p.read_bytes()) for p in outside.iterdir()] == [("surface.pt", b"someone else's file")]


def test_the_cli_names_the_linked_folder_and_exits_2(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    shutil.rmtree(scan.root / "model")
    (scan.root / "model").symlink_to(tmp_path)
    result = CliRunner().invoke(app, ["train", str(scan.root), "--preset", "tiny"])
    message = " ".join(result.output.split())  # rich wraps long lines
    assert result.exit_code == 2 and "model: is a symbolic link" in message
    assert "Traceback" not in result.output


# -- atomic stages --------------------------------------------------------------------------------
def test_a_failing_stage_leaves_the_old_complete_result(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    def result() -> dict[str, bytes]:  # the model, less the checkpoint (working state, not a result)
        return {p.name: p.read_bytes() for p in scan.model_dir.iterdir() if p.name != "checkpoint.pt"}

    before = result()
    (scan.root / "poses" / "transforms.json").write_text("{}")  # the new run fails on its input
    with pytest.raises(Exception, match="transforms.json"):
        run_stage(scan.root, "train", TINY)
    assert result() == before and set(before) == {"surface.pt", "infill.pt", "train_metrics.json"}
    assert read_record(scan, "train")["state"] == "started" and not stage_done(scan, "train")


def test_a_swap_cut_short_by_a_crash_rolls_forward_to_the_whole_new_result(tmp_path):
    scan = ScanFolder(tmp_path / "scan")
    for name, text in (("images", "old"), ("masks", "old")):
        atomic_write_bytes(scan.root / name / "f.png", text.encode())
    staged = scan.staged("process", ("images", "masks"))
    for name in ("images", "masks"):
        atomic_write_bytes(getattr(staged, f"{name}_dir") / "f.png", b"new")
    # the crash: journal written, images swapped, masks not yet
    (scan.stages_dir / ".process.swap.json").write_text(json.dumps({"folders": ["images", "masks"]}))
    (scan.root / "images").rename(scan.root / ".images.old")
    (scan.root / ".images.new").rename(scan.root / "images")
    scan.recover("process", ("images", "masks"))
    assert (scan.root / "images" / "f.png").read_bytes() == (scan.root / "masks" / "f.png").read_bytes() == b"new"
    assert sorted(p.name for p in scan.root.iterdir()) == ["images", "masks", "stages"]


def test_a_staged_view_reads_paths_from_files_as_they_will_be_after_the_swap(tmp_path):
    scan = ScanFolder(tmp_path / "scan")
    atomic_write_bytes(scan.root / "images" / "f.png", b"old")
    staged = scan.staged("process", ("images",))
    atomic_write_bytes(staged.images_dir / "f.png", b"new")
    assert staged.resolve_inside("images/f.png").read_bytes() == b"new"
    staged.mark_done("process", {"n": 1})
    assert not scan.is_done("process")  # held back until the commit
    scan.commit(staged, "process")
    assert (scan.root / "images" / "f.png").read_bytes() == b"new" and scan.stage_info("process") == {"n": 1}


def test_export_removes_the_old_verdict_before_anything_else(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    atomic_write_bytes(scan.asset_dir / "gate.json", b'{"pass": true, "checks": []}')
    atomic_write_bytes(scan.asset_dir / "splat.ply", b"old splat")
    scan.mark_done("export", {"pass": True})
    (scan.model_dir / "surface.pt").write_bytes(b"not a checkpoint")  # export fails on loading it
    with pytest.raises(Exception):
        perform(scan.root, "export", {})
    assert not (scan.asset_dir / "gate.json").exists() and not scan.is_done("export")
    assert (scan.asset_dir / "splat.ply").read_bytes() == b"old splat"


# -- fingerprints ---------------------------------------------------------------------------------
def interrupted(scan: ScanFolder) -> None:
    """As a killed `station train` leaves the scan: a started record and a checkpoint in the fresh folder."""
    from station.pipeline import output_digest, scan_stage_key

    upstream = {"process": output_digest(scan, spec("process"))}
    write_started(scan, "train", scan_stage_key(scan, spec("train"), TINY, upstream))
    staging = scan.staging_path("model")
    staging.mkdir()
    shutil.copy(scan.model_dir / "checkpoint.pt", staging / "checkpoint.pt")


def test_an_interrupted_training_resumes_on_the_same_views(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    interrupted(scan)
    report = run_stage(scan.root, "train", TINY)
    assert report.resumed_from == report.steps  # the checkpoint was at the last step: nothing left to train


def test_after_the_views_change_training_starts_over_instead_of_resuming(trained, tmp_path, caplog):
    scan = copy_of(trained, tmp_path)
    interrupted(scan)
    first, second = sorted(scan.images_dir.iterdir())[:2]
    assert first.read_bytes() != second.read_bytes()
    shutil.copy(second, first)  # the views are new (`import` or `process` again)
    report = run_stage(scan.root, "train", TINY)
    assert report.resumed_from == 0 and report.steps > 0
    # the stale folder was dropped on the key alone; the trainer's own check never had to refuse it
    assert "other posed views" not in caplog.text


def test_a_checkpoint_from_other_views_is_not_resumed_by_the_trainer(trained, tmp_path):
    from station.ngs.dataset import load_scene
    from station.ngs.presets import make_config
    from station.ngs.trainer import Trainer

    scan = copy_of(trained, tmp_path)
    cfg = make_config("ngs", "tiny")
    scene = load_scene(scan.root, downscale=cfg.downscale, seed=cfg.seed)
    assert Trainer(scene, cfg, scan.model_dir, inputs="other views").load_checkpoint() == 0
    recorded = Trainer(scene, cfg, scan.model_dir, inputs="")
    assert recorded.load_checkpoint() == 0  # the pipeline always records a fingerprint
    from station.pipeline import inputs_fingerprint

    same = Trainer(scene, cfg, scan.model_dir, inputs=inputs_fingerprint(scan, spec("train")))
    assert same.load_checkpoint() == cfg.steps


def test_cleaning_a_stale_stage_drops_its_fresh_folder_only(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    interrupted(scan)
    clean_stage(scan, spec("train"))
    assert not scan.staging_path("model").exists() and (scan.model_dir / "surface.pt").is_file()


# -- errors and exit codes --------------------------------------------------------------------------
def _cli(body) -> typer.Typer:
    cli = typer.Typer()
    cli.callback()(lambda: None)
    cli.command("go")(exits_on_station_errors(body))
    return cli


def test_a_full_disk_is_the_documented_disk_full_error_exit_3():
    def body() -> None:
        with open("/dev/full", "wb") as handle:  # the kernel answers every write with ENOSPC
            handle.write(b"x" * 8192)
            handle.flush()

    result = CliRunner().invoke(_cli(body), ["go"])
    assert result.exit_code == 3 and "disk is full" in result.output and "Traceback" not in result.output


def test_an_unexpected_error_is_one_line_and_a_pointer_to_verbose():
    result = CliRunner().invoke(_cli(lambda: {}["missing"]), ["go"])
    assert result.exit_code == INTERNAL_EXIT_CODE
    assert "unexpected KeyError" in result.output and "--verbose" in result.output
    assert "Traceback" not in result.output


def test_a_quarantined_export_is_exit_1_after_the_verdict_and_swapped_in_whole(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    atomic_write_bytes(scan.asset_dir / "stale.txt", b"an earlier run's file")
    result = CliRunner().invoke(app, ["export", str(scan.root), "--json"])
    verdict = json.loads(result.stdout)
    assert result.exit_code == (0 if verdict["pass"] else 1), result.output
    if not verdict["pass"]:
        assert "failed the quality gate" in result.stderr
    assert all(Path(path).parent == scan.asset_dir and Path(path).is_file() for path in verdict["files"].values())
    assert not (scan.asset_dir / "stale.txt").exists()  # the new asset/ replaced the old one whole
    assert stage_done(scan, "export") and json.loads((scan.asset_dir / "gate.json").read_text())["pass"] == verdict["pass"]


def test_records_are_never_written_or_removed_through_a_linked_stages_folder(trained, tmp_path):
    scan = copy_of(trained, tmp_path)
    outside = tmp_path / "outside"
    shutil.move(scan.stages_dir, outside)
    scan.stages_dir.symlink_to(outside)
    before = sorted(p.name for p in outside.iterdir())
    for attempt in (lambda: clean_stage(scan, spec("train")), lambda: write_started(scan, "train", "k"),
                    lambda: scan.mark_done("train", {}), lambda: run_stage(scan.root, "train", TINY)):
        with pytest.raises(ScanFolderError, match="symbolic link"):
            attempt()
    assert sorted(p.name for p in outside.iterdir()) == before


def test_a_missing_scan_folder_is_named_and_not_created(tmp_path):
    result = CliRunner().invoke(app, ["train", str(tmp_path / "nowhere")])
    assert result.exit_code == 2 and "scan folder not found" in result.output
    assert not (tmp_path / "nowhere").exists()
