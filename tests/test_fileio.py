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


def test_a_killed_runs_stage_goes_at_the_next_run_and_nothing_else(tmp_path: Path) -> None:
    """kill -9 leaves ``.out.tmp-HOST-PID-*``: the next run into ``out`` removes it when
    that process is gone, and leaves other hosts' and live processes' stages alone."""
    import os
    import subprocess
    import sys

    from skinpipe.fileio import _stage_prefix, staged_output_directory

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    target = tmp_path / "out"
    prefix = _stage_prefix(target)
    ours_dead = tmp_path / (prefix.replace(f"-{os.getpid()}-", f"-{dead.pid}-") + "abc123")
    ours_live = tmp_path / (prefix + "live99")
    other_host = tmp_path / f".out.tmp-elsewhere-{dead.pid}-xyz"
    users = tmp_path / ".out.tmp-notes"
    for folder in (ours_dead, ours_live, other_host, users):
        folder.mkdir()
        (folder / "f.txt").write_text("x")
    with staged_output_directory(target, "test") as out:
        (out.path / "a.txt").write_text("a")
    assert not ours_dead.exists()
    assert ours_live.exists() and other_host.exists() and users.exists()
    assert (target / "a.txt").read_text() == "a"
