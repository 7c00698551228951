"""Atomic outputs: what a killed process leaves is found, records are relocated."""

from __future__ import annotations

import os
from pathlib import Path

from skinpipe.fileio import atomic_directory, relocate_paths, stale_siblings


def test_stale_temporaries_are_found(tmp_path: Path) -> None:
    target = tmp_path / "ingest"
    (tmp_path / ".ingest.tmp-abc").mkdir()
    (tmp_path / ".ingest.old-def").mkdir()
    (tmp_path / ".fit.tmp-xyz").mkdir()  # another task's
    assert [p.name for p in stale_siblings(target)] == [".ingest.old-def", ".ingest.tmp-abc"]
    with atomic_directory(target) as tmp:
        (tmp / "x.txt").write_text("1")
    assert (target / "x.txt").read_text() == "1"


def test_relocate_paths_only_under_the_old_root() -> None:
    old, new = f"{os.sep}r{os.sep}.a.tmp-1", f"{os.sep}r{os.sep}a"
    doc = {"csv": f"{old}{os.sep}f.csv", "n": 3, "list": [old, f"{old}x{os.sep}g"],
           "other": f"{os.sep}elsewhere"}
    assert relocate_paths(doc, old, new) == {
        "csv": f"{new}{os.sep}f.csv", "n": 3, "list": [new, f"{old}x{os.sep}g"],
        "other": f"{os.sep}elsewhere"}
