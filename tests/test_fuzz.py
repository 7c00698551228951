"""The readers that could kill the interpreter, fuzzed briefly (tools/fuzz_readers.py):
USD text, OBJ/PLY, EXR/TIFF headers. The fuzzer runs in a child process, so a crash is
a failed test naming the signal, not a dead test run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "fuzz_readers.py"


@pytest.mark.parametrize("target", ["usd", "obj", "ply", "exr", "tif"])
def test_mutated_files_never_crash_a_reader(target: str) -> None:
    proc = subprocess.run([sys.executable, str(TOOL), "--target", target, "--examples", "40"],
                          capture_output=True, text=True, timeout=300,
                          cwd=TOOL.parents[1])
    assert proc.returncode == 0, (
        f"signal {-proc.returncode}" if proc.returncode < 0 else proc.stderr[-3000:])
    assert "no crash" in proc.stdout
