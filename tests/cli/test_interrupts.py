"""Ctrl-C at several moments of each long verb: exit 130, one line saying so, no
traceback, nothing left in or beside -o. The moments are progress lines, not times, so
a loaded machine meets the same ones; Ctrl-C goes to the whole process group, as a
terminal sends it (the children get it too)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from skinpipe.interrupts import install, raise_if_child_interrupted, raise_if_interrupted, restore

ROOT = Path(__file__).resolve().parents[2]
CAPTURES = ROOT / "skinpipe" / "samples" / "captures"


def interrupt_when(args: list[str], marker: str, cwd: Path) -> tuple[int, str]:
    """Run ``skinpipe ARGS``, send SIGINT to its process group when ``marker`` appears on
    its stderr, and return its exit code and stderr."""
    # as from a terminal: a suite run as a script's background job inherits SIGINT
    # ignored, which skinpipe (as Python) keeps, and no Ctrl-C would then reach it
    proc = subprocess.Popen([sys.executable, "-m", "skinpipe", *args], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    seen = bytearray()
    found = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        while chunk := proc.stderr.read1(4096):
            seen.extend(chunk)
            if marker.encode() in seen:
                found.set()
        found.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    found.wait(600)
    if proc.poll() is None and marker.encode() in seen:
        os.killpg(proc.pid, signal.SIGINT)
    code = proc.wait(600)
    reader.join(10)
    text = seen.decode(errors="replace")
    assert marker in text, f"never reached {marker!r}: {text[-1500:]}"
    return code, text


def assert_interrupted(verb: str, code: int, err: str, workdir: Path, out: str) -> None:
    assert code == 130, (code, err[-2000:])
    assert "Traceback" not in err, err[-2000:]
    # the last line skinpipe wrote (PoCL's compiler, stopped mid-build, may add
    # "1 error generated." of its own, and its "1" may land before our line)
    ours = [line[line.index("skinpipe "):] if "skinpipe " in line else line
            for line in err.replace("\r", "\n").splitlines()
            if "skinpipe " in line or line.startswith("[")]
    assert ours[-1] == f"skinpipe {verb}: interrupted; no partial output was kept", ours[-3:]
    left = sorted(p.name for p in workdir.iterdir() if out in p.name)
    assert left == [], f"left behind: {left}"


# the demo's render stages are the render verb's (test_render_stops_on_ctrl_c) and a
# second region's fit stops as "[2/6]" does: they run with the slow tests, where a stop
# at each still costs 8-22 s of demo
DEMO_MOMENTS = ["preparing the scan", "[2/6]",
                *(pytest.param(m, marks=pytest.mark.slow)
                  for m in ("fit chin", "author ", "% irradiance", "% diffusion"))]


@pytest.mark.parametrize("marker", DEMO_MOMENTS)
def test_demo_stops_on_ctrl_c(tmp_path: Path, marker: str) -> None:
    code, err = interrupt_when(["demo", "-o", "out"], marker, tmp_path)
    assert_interrupted("demo", code, err, tmp_path, "out")


@pytest.mark.parametrize("marker", ["chin: ", "[1/2]"])
def test_ingest_stops_on_ctrl_c(tmp_path: Path, marker: str) -> None:
    caps = tmp_path / "caps"
    shutil.copytree(CAPTURES, caps)
    doc = json.loads((caps / "capture.json").read_text())
    doc["regions"] = {k: v for k, v in doc["regions"].items() if k in ("forehead", "chin")}
    (caps / "capture.json").write_text(json.dumps(doc))
    code, err = interrupt_when(["ingest", "caps", "-o", "out"], marker, tmp_path)
    assert_interrupted("ingest", code, err, tmp_path, "out")


@pytest.fixture(scope="module")
def demo_scene(demo_run: tuple[Path, str, str]) -> Path:
    return demo_run[0] / "scene.usda"


@pytest.mark.parametrize("marker", ["% bvh", "% irradiance", "% diffusion", "% shade"])
def test_render_stops_on_ctrl_c(tmp_path: Path, demo_scene: Path, marker: str) -> None:
    code, err = interrupt_when(["render", str(demo_scene), "--texture-size", "2048",
                                "-o", "out"], marker, tmp_path)
    assert_interrupted("render", code, err, tmp_path, "out")


@pytest.mark.parametrize("marker", ["worker(s)", "ingest"])
def test_batch_stops_on_ctrl_c(tmp_path: Path, marker: str) -> None:
    subjects = []
    for name in ("a", "b", "c"):
        shutil.copytree(CAPTURES, tmp_path / f"caps_{name}")
        subjects.append({"name": name, "captures": f"caps_{name}"})
    (tmp_path / "batch.json").write_text(json.dumps({"subjects": subjects}))
    code, err = interrupt_when(["batch", "batch.json", "--stages", "ingest,fit",
                                "--local-workers", "2", "-o", "out"], marker, tmp_path)
    assert_interrupted("batch", code, err, tmp_path, "out")


@pytest.fixture
def sigint_as_from_a_terminal() -> Iterator[None]:
    """SIGINT handled as Python handles it in a terminal, for the test's duration (a
    suite run as a script's background job inherits it ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.usefixtures("sigint_as_from_a_terminal")
def test_an_interrupt_a_library_swallowed_still_stops_the_work() -> None:
    """casadi turns a KeyboardInterrupt in its callback into IPOPT's
    NonIpopt_Exception_Thrown: the flag set by the handler still stops the fit."""
    previous = install()
    try:
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    finally:
        restore(previous)
    install()  # a new verb starts with the flag cleared
    try:
        raise_if_interrupted()
    finally:
        restore(previous)
    with pytest.raises(KeyboardInterrupt):
        raise_if_child_interrupted(-signal.SIGINT)
    raise_if_child_interrupted(-signal.SIGSEGV)
