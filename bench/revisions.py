"""The two trees of a bench's `--against REV`: revision REV unpacked beside the run, and this one's label."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def unpack(rev: str, dest: Path) -> str:
    """Revision `rev`'s files (git archive, so no checkout or worktree is touched) into the folder `dest`;
    returns its short commit hash, the label a result keeps (a name such as HEAD moves on)."""
    commit = short_hash(rev)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return commit


def unpack_as(rev: str, dest: Path, package: str) -> str:
    """Revision `rev`'s `station` package into `dest` as `package`, its own imports renamed to match, so that one
    process can import both trees side by side; returns its short commit hash."""
    with_files = dest / "tree"
    with_files.mkdir()
    commit = unpack(rev, with_files)
    shutil.move(with_files / "station", dest / package)
    shutil.rmtree(with_files)
    imports = re.compile(r"^(\s*)(from|import) station\b", re.MULTILINE)
    for source in (dest / package).rglob("*.py"):
        source.write_text(imports.sub(rf"\1\2 {package}", source.read_text()))
    return commit


def working_tree() -> str:
    """This tree's label in a result: its commit, and that uncommitted edits may be in it."""
    return f"{short_hash('HEAD')} (working tree)"


def short_hash(rev: str) -> str:
    """The short hash of the commit `rev` names."""
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", f"{rev}^{{commit}}"],
                          capture_output=True, text=True, check=True).stdout.strip()
