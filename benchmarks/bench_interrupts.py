"""Benchmark: how soon Ctrl-C stops each long verb, against how long it would run on.

    python benchmarks/bench_interrupts.py [-o benchmarks/results/interrupts.json]

Runs `skinpipe demo`, `ingest`, `render` (the demo's scene at texture 2048) and `batch`
(three subjects, two local workers) once to the end, and once more for each moment
tests/cli/test_interrupts.py interrupts them at: SIGINT goes to the process group when
the moment's progress line appears. Reports per moment the seconds from the signal to
the process's exit (exit 130, nothing left beside ``-o``), and as the peer the seconds
the uninterrupted run went on from the same line to its end: what a user who pressed
Ctrl-C would otherwise wait.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
CAPTURES = ROOT / "skinpipe" / "samples" / "captures"

VERBS: dict[str, tuple[list[str], list[str]]] = {
    "demo": (["demo", "-o", "out"],
             ["preparing the scan", "[2/6]", "fit chin", "author ", "% irradiance",
              "% diffusion"]),
    "ingest": (["ingest", "caps", "-o", "out"], ["chin: ", "[1/2]"]),
    "render": (["render", "scene/scene.usda", "--texture-size", "2048", "-o", "out"],
               ["% bvh", "% irradiance", "% diffusion", "% shade"]),
    "batch": (["batch", "batch.json", "--stages", "ingest,fit", "--local-workers", "2",
               "-o", "out"], ["worker(s)", "ingest"]),
}
"""Each verb's arguments (run in a folder prepared by :func:`prepare`) and the progress
lines at which it is interrupted."""


def prepare(folder: Path) -> None:
    """The inputs every verb reads: the sample captures (two regions for ``ingest``,
    three subjects for ``batch``) and the demo's scene."""
    caps = folder / "caps"
    shutil.copytree(CAPTURES, caps)
    doc = json.loads((caps / "capture.json").read_text())
    doc["regions"] = {k: v for k, v in doc["regions"].items() if k in ("forehead", "chin")}
    (caps / "capture.json").write_text(json.dumps(doc))
    subjects = []
    for name in ("a", "b", "c"):
        shutil.copytree(CAPTURES, folder / f"caps_{name}")
        subjects.append({"name": name, "captures": f"caps_{name}"})
    (folder / "batch.json").write_text(json.dumps({"subjects": subjects}))
    subprocess.run([sys.executable, "-m", "skinpipe", "demo", "-o", "scene"], cwd=folder,
                   check=True, capture_output=True)


def run(args: list[str], cwd: Path, marker: str | None, stop: bool
        ) -> tuple[int, float, float]:
    """Run ``skinpipe ARGS`` in ``cwd``; with ``stop``, SIGINT to its process group at
    the first stderr line holding ``marker``. (exit code, seconds from the marker to the
    signal's send or to the end without one, seconds from there to the exit)."""
    proc = subprocess.Popen([sys.executable, "-m", "skinpipe", *args], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    start = time.perf_counter()
    seen = bytearray()
    at: list[float] = []

    def read() -> None:
        assert proc.stderr is not None
        while chunk := proc.stderr.read1(4096):
            seen.extend(chunk)
            if marker is not None and not at and marker.encode() in seen:
                at.append(time.perf_counter())
                if stop:
                    os.killpg(proc.pid, signal.SIGINT)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    code = proc.wait()
    end = time.perf_counter()
    reader.join(10)
    if marker is not None and not at:
        raise RuntimeError(f"skinpipe {' '.join(args)} never printed {marker!r}: "
                           f"{seen.decode(errors='replace')[-800:]}")
    mark = at[0] if at else start
    return code, mark - start, end - mark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", type=Path,
                        default=Path("benchmarks/results/interrupts.json"))
    parser.add_argument("--verbs", default=",".join(VERBS),
                        help="comma-separated verbs to measure (default: all)")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        prepare(folder)
        for verb in args.verbs.split(","):
            argv, moments = VERBS[verb]
            for marker in moments:
                code, _, rest_s = run(argv, folder, marker, stop=False)
                if code != 0:
                    raise RuntimeError(f"skinpipe {verb} failed (exit {code})")
                shutil.rmtree(folder / "out")
                code, _, stop_s = run(argv, folder, marker, stop=True)
                left = sorted(p.name for p in folder.iterdir() if "out" in p.name)
                rows.append({"verb": verb, "moment": marker, "exit": code,
                             "left_behind": left, "stop_seconds": round(stop_s, 3),
                             "would_run_on_seconds": round(rest_s, 3),
                             "ratio": round(stop_s / max(rest_s, 1e-9), 4)})
                for name in left:
                    shutil.rmtree(folder / name, ignore_errors=True)
                print(f"{verb:<7} at {marker!r:<22} stopped in {stop_s:5.2f} s (exit {code}"
                      f"{', left ' + ', '.join(left) if left else ''}) against "
                      f"{rest_s:6.2f} s to run on: {stop_s / max(rest_s, 1e-9):.3f}x",
                      flush=True)
    doc = {"benchmark": "interrupts", "cpus": os.cpu_count(), "rows": rows,
           "slowest_stop_seconds": max(r["stop_seconds"] for r in rows),
           "all_exit_130_nothing_left": all(r["exit"] == 130 and not r["left_behind"]
                                            for r in rows)}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"slowest stop {doc['slowest_stop_seconds']:.2f} s; every run exit 130 with "
          f"nothing left: {doc['all_exit_130_nothing_left']}")


if __name__ == "__main__":
    main()
