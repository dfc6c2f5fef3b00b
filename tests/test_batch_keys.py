"""Stage keys and records: what makes finished work count as finished, and what makes it stale.

These work on small hand-made scan folders (a manifest over a few raw files, stage outputs as
plain files): the key logic only hashes files, so no stage needs to run here.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from station.batch.stages import (
    STAGES,
    clean_stage,
    code_version,
    finished_record,
    output_digest,
    resumable,
    scan_stage_key,
    sweep_temp_files,
    write_done,
    write_started,
)
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_json, sha256_file

pytestmark = pytest.mark.no_kernels

PROCESS, TRAIN, EXPORT = STAGES


def make_scan(root: Path) -> ScanFolder:
    """Two raws in a manifest, a finished capture, and the files each stage would have written."""
    scan = ScanFolder(root)
    entries = []
    for name in ("plate_e0.dng", "e0_a000.dng"):
        path = scan.raw_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(name.encode() * 100)
        entries.append(ManifestEntry(f"raw/{name}", sha256_file(path), 10.0, 0.0,
                                     "plate" if "plate" in name else "shot", 0.03, 100, "2026-01-01T00:00:00Z"))
    scan.write_manifest(entries)
    atomic_write_json(scan.scan_json, {"plan": {"elevations_deg": [10.0], "azimuths": 1}})
    scan.mark_done("capture", {"frames": 2})
    for relative in ("images/e0_a000.png", "masks/e0_a000.png", "poses/transforms.json", "poses/colmap/cameras.bin",
                     "model/surface.pt", "model/checkpoint.pt", "asset/splat.ply"):
        (scan.root / relative).parent.mkdir(parents=True, exist_ok=True)
        (scan.root / relative).write_bytes(relative.encode())
    for stage in ("process", "train", "export"):
        scan.mark_done(stage, {})
    return scan


@pytest.fixture
def scan(tmp_path) -> ScanFolder:
    return make_scan(tmp_path / "scan")


def keys(scan: ScanFolder, preset: str = "tiny") -> dict[str, str]:
    """Each stage's key as the runner computes it, with the current files as the upstream outputs."""
    upstream = {spec.name: output_digest(scan, spec) for spec in STAGES}
    params = {"process": {}, "train": {"method": "ngs", "preset": preset}, "export": {}}
    return {spec.name: scan_stage_key(scan, spec, params[spec.name], upstream) for spec in STAGES}


def test_a_key_is_stable_while_nothing_changes(scan):
    assert keys(scan) == keys(scan)


def test_a_raw_whose_bytes_change_after_capture_makes_processing_stale(scan):
    before = keys(scan)
    (scan.raw_dir / "e0_a000.dng").write_bytes(b"bit rot" * 100)  # the manifest still holds the old sha256
    after = keys(scan)
    assert after["process"] != before["process"]
    assert after["train"] == before["train"]  # train is keyed on process's outputs, which have not changed yet


def test_a_new_preset_makes_training_and_only_training_stale(scan):
    before, after = keys(scan, "tiny"), keys(scan, "fast")
    assert after["train"] != before["train"]
    assert (after["process"], after["export"]) == (before["process"], before["export"])


def test_changed_upstream_outputs_make_the_downstream_stages_stale(scan):
    before = keys(scan)
    (scan.root / "poses" / "transforms.json").write_bytes(b"{}")
    after = keys(scan)
    assert after["process"] == before["process"]
    assert after["train"] != before["train"] and after["export"] != before["export"]


def test_the_code_version_covers_each_stage_own_source():
    assert code_version(PROCESS.code) != code_version(TRAIN.code) != code_version(EXPORT.code)
    assert code_version(TRAIN.code) == code_version(TRAIN.code)


def test_a_stage_is_finished_only_under_its_key_and_while_every_output_verifies(scan):
    key = keys(scan)["process"]
    write_done(scan, "process", key, output_digest(scan, PROCESS), {"flags": []})
    assert finished_record(scan, PROCESS, key)["outputs"] == output_digest(scan, PROCESS)
    assert finished_record(scan, PROCESS, "another key") is None
    (scan.root / "masks" / "e0_a000.png").write_bytes(b"truncated")
    assert finished_record(scan, PROCESS, key) is None


def test_an_unreadable_record_counts_as_not_finished(scan):
    key = keys(scan)["process"]
    write_done(scan, "process", key, output_digest(scan, PROCESS), {})
    (scan.stages_dir / "process.key.json").write_bytes(b'{"stage": "proc')  # half a record (not our writer)
    assert finished_record(scan, PROCESS, key) is None


def test_training_outputs_exclude_its_checkpoint_but_cleaning_removes_it(scan):
    assert "model/checkpoint.pt" not in output_digest(scan, TRAIN)
    half_done = scan.staging_path("model") / "checkpoint.pt"  # an interrupted run's fresh folder
    half_done.parent.mkdir()
    half_done.write_bytes(b"stale")
    clean_stage(scan, TRAIN)
    assert not (scan.model_dir / "checkpoint.pt").exists() and not scan.staging_path("model").exists()
    assert not scan.is_done("train")
    # the last complete result stays until a new run swaps its own in
    assert (scan.model_dir / "surface.pt").exists()
    assert (scan.images_dir / "e0_a000.png").exists() and (scan.asset_dir / "splat.ply").exists()


def test_cleaning_never_deletes_through_a_symlinked_stage_folder(scan, tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "checkpoint.pt").write_bytes(b"not the scan's")
    (outside / "surface.pt").write_bytes(b"not the scan's")
    (scan.root / "model" / "surface.pt").unlink()
    (scan.root / "model" / "checkpoint.pt").unlink()
    (scan.root / "model").rmdir()
    (scan.root / "model").symlink_to(outside)
    assert output_digest(scan, TRAIN) == {"stages/train.json": output_digest(scan, TRAIN)["stages/train.json"]}
    clean_stage(scan, TRAIN)
    assert sorted(p.name for p in outside.iterdir()) == ["checkpoint.pt", "surface.pt"]


def test_only_a_started_record_under_the_same_key_may_be_resumed(scan):
    write_started(scan, "train", "k1")
    assert resumable(scan, TRAIN, "k1")
    assert not resumable(scan, TRAIN, "k2")
    write_done(scan, "train", "k1", output_digest(scan, TRAIN), {})
    assert not resumable(scan, TRAIN, "k1")


def test_temp_files_of_killed_writers_are_swept_and_nothing_else(scan):
    left = [scan.images_dir / ".e0_a001.x1y2z3.tmp.png", scan.model_dir / ".checkpoint.pt.ab12cd.tmp"]
    for path in left:
        path.write_bytes(b"half")
    (scan.root / ".hidden_note").write_bytes(b"keep")
    assert "images/.e0_a001.x1y2z3.tmp.png" not in output_digest(scan, PROCESS)  # never part of an output
    assert sorted(sweep_temp_files(scan)) == ["images/.e0_a001.x1y2z3.tmp.png", "model/.checkpoint.pt.ab12cd.tmp"]
    assert not any(path.exists() for path in left) and (scan.root / ".hidden_note").exists()
