"""Benchmark: wall time of the fit stage of a batch on 1, 2 and 4 local Dask workers.

Twelve subjects share the bundled capture set (each gets its own outputs). Their
ingest runs once first; then, for each worker count, every fit directory is removed and
``--stages fit`` runs again (ingest is a cache hit), so the timing is the 72 region fits
(6 regions x 12 subjects) plus scheduling. Serial peer: the same fits in one process,
one after another, measured in the same run. Writes JSON and a table.

    python benchmarks/bench_batch.py [--subjects 12] [--workers 1,2,4]
                                     [-o benchmarks/results/batch_scaling.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from distributed import Client, LocalCluster

from skinpipe.profile.fit import FitOptions, fit_sum_of_gaussians
from skinpipe.profile.io import read_profile_csv
from skinpipe.workflow.batch import read_batch, run_batch

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=12)
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("-o", "--output", type=Path,
                    default=ROOT / "benchmarks" / "results" / "batch_scaling.json")
    args = ap.parse_args()
    counts = [int(w) for w in args.workers.split(",")]
    work = Path(tempfile.mkdtemp(prefix="skinpipe-bench-batch-"))
    try:
        batch = work / "batch.json"
        captures = ROOT / "skinpipe" / "samples" / "captures"
        batch.write_text(json.dumps({"defaults": {"captures": str(captures), "k": 6},
                                     "subjects": [{"name": f"s{i:02d}"}
                                                  for i in range(args.subjects)]}))
        subjects = read_batch(batch)
        out = work / "out"
        with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as c, \
                Client(c) as client:
            run_batch(client, subjects, out, ("ingest",))
        # the serial peer: the same 6 x N fits in this process
        start = time.perf_counter()
        for s in subjects:
            for csv in sorted((out / s.name / "ingest").glob("*.csv")):
                fit_sum_of_gaussians(read_profile_csv(csv), FitOptions(k=6, free_scale=True))
        serial = time.perf_counter() - start
        rows = []
        for n in counts:
            for s in subjects:
                shutil.rmtree(out / s.name / "fit", ignore_errors=True)
            with LocalCluster(n_workers=n, threads_per_worker=1,
                              dashboard_address=None) as c, Client(c) as client:
                result = run_batch(client, subjects, out, ("fit",))
            fits = [t for t in result.tasks if t["stage"] == "fit"]
            assert all(t["status"] == "done" for t in fits), "a fit failed"
            rows.append({"workers": n, "wall_seconds": result.seconds, "fits": len(fits),
                         "task_seconds_sum": sum(t["seconds"] for t in fits),
                         "speedup_vs_serial": serial / result.seconds})
    finally:
        shutil.rmtree(work, ignore_errors=True)
    doc = {"benchmark": "batch_fit_scaling", "subjects": args.subjects,
           "serial_seconds": serial, "rows": rows,
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "platform": platform.platform()}}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"{args.subjects} subjects, {rows[0]['fits']} fits; serial in one process "
          f"{serial:.1f} s ({os.cpu_count()} CPUs)")
    print(f"{'workers':>8} {'wall s':>8} {'sum of task s':>14} {'vs serial':>10}")
    for r in rows:
        print(f"{r['workers']:>8} {r['wall_seconds']:>8.1f} {r['task_seconds_sum']:>14.1f} "
              f"{r['speedup_vs_serial']:>9.2f}x")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
