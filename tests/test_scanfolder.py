"""The scan-folder contract: atomic writes, the manifest, and refusal of escaping paths."""

import pytest

from station.errors import ScanFolderError
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_bytes, sha256_bytes


def test_atomic_write_replaces_whole_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "a" / "frame.bin"
    atomic_write_bytes(target, b"old")
    atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"new content"
    assert [p.name for p in target.parent.iterdir()] == ["frame.bin"]


def test_manifest_round_trip_and_verification(tmp_path):
    scan = ScanFolder(tmp_path)
    atomic_write_bytes(scan.raw_dir / "e0_a0.dng", b"raw bytes")
    entry = ManifestEntry("raw/e0_a0.dng", sha256_bytes(b"raw bytes"), 10.0, 0.0, "shot", 0.01, 100, "2026-01-01T00:00:00Z")
    scan.write_manifest([entry])
    assert scan.read_manifest() == [entry]
    assert scan.verify_entry(entry)
    (scan.raw_dir / "e0_a0.dng").write_bytes(b"corrupted")
    assert not scan.verify_entry(entry)


def test_paths_escaping_the_folder_are_refused(tmp_path):
    scan = ScanFolder(tmp_path / "scan")
    with pytest.raises(ScanFolderError, match="outside the scan folder"):
        scan.resolve_inside("../../etc/passwd")


def test_malformed_manifest_line_names_the_file(tmp_path):
    scan = ScanFolder(tmp_path)
    scan.manifest_path.write_text('{"file": "raw/x.dng"}\n')
    with pytest.raises(ScanFolderError, match="manifest.jsonl"):
        scan.read_manifest()
