"""The scan-folder contract: atomic writes, the manifest, and refusal of escaping paths."""

import stat
import subprocess
import sys

import pytest

from station.errors import ScanFolderError
from station.scanfolder import ManifestEntry, ScanFolder, atomic_write_bytes, remove_tree, sha256_bytes

pytestmark = pytest.mark.no_kernels


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


def test_a_stage_folder_that_is_a_link_or_a_file_is_refused(tmp_path):
    scan = ScanFolder(tmp_path / "scan")
    scan.root.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (scan.root / "masks").symlink_to(tmp_path / "elsewhere")
    (scan.root / "model").write_bytes(b"a file where a folder belongs")
    with pytest.raises(ScanFolderError, match="masks: is a symbolic link"):
        scan.owned_folder("masks")
    with pytest.raises(ScanFolderError, match="expected a folder"):
        scan.owned_folder("model")
    assert scan.owned_folder("images") == scan.root / "images"  # absent is fine: the stage creates it


def test_removing_a_linked_tree_removes_the_link_and_never_its_target(tmp_path):
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "keep.png").write_bytes(b"not the scan's")
    link = tmp_path / "scan" / ".masks.new"
    link.parent.mkdir()
    link.symlink_to(target)
    remove_tree(link)
    assert not link.exists() and (target / "keep.png").read_bytes() == b"not the scan's"


def test_a_staged_view_writes_only_into_its_fresh_folder_until_the_commit(tmp_path):
    scan = ScanFolder(tmp_path / "scan")
    atomic_write_bytes(scan.model_dir / "surface.pt", b"old")
    staged = scan.staged("train", ("model",))
    atomic_write_bytes(staged.model_dir / "surface.pt", b"new")
    assert (scan.model_dir / "surface.pt").read_bytes() == b"old" and staged.images_dir == scan.images_dir
    scan.commit(staged, "train")
    assert (scan.model_dir / "surface.pt").read_bytes() == b"new"
    assert sorted(p.name for p in scan.root.iterdir()) == ["model", "stages"]


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_written_files_honour_the_process_umask(tmp_path, umask, mode):
    script = (f"import os; os.umask({umask:#o}); from pathlib import Path; "
              "from station.scanfolder import atomic_write_bytes, atomic_write_with; "
              f"atomic_write_bytes(Path({str(tmp_path / 'a.json')!r}), b'{{}}'); "
              f"atomic_write_with(Path({str(tmp_path / 'b.png')!r}), lambda p: p.write_bytes(b'x'))")
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    assert [stat.S_IMODE((tmp_path / name).stat().st_mode) for name in ("a.json", "b.png")] == [mode, mode]
