"""bench/revisions.py: an older revision unpacked under another package name imports on its own code alone,
so `bench/raster.py --against` times that revision, not this tree under two names."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

IMPORT_BOTH = """
import sys
sys.path[:0] = [{old!r}, {root!r}]
import station_before.ngs.trainer, station_before.ngs.raster
leaked = sorted(m for m in sys.modules if m == "station" or m.startswith("station."))
outside = sorted(m for m, mod in sys.modules.items()
                 if m.startswith("station_before") and not str(getattr(mod, "__file__", "") or {old!r}).startswith({old!r}))
import station.ngs.raster
print(leaked, outside, station.ngs.raster.__file__.startswith({root!r}))
"""


def test_a_revision_unpacked_as_another_package_imports_none_of_this_tree(tmp_path: Path):
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from revisions import unpack_as
    finally:
        sys.path.remove(str(ROOT / "bench"))
    commit = unpack_as("HEAD", tmp_path, "station_before")
    assert commit and (tmp_path / "station_before" / "ngs" / "raster.py").is_file()
    assert not (tmp_path / "station").exists()
    done = subprocess.run([sys.executable, "-c", IMPORT_BOTH.format(old=str(tmp_path), root=str(ROOT))],
                          capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "[]", "True"]
