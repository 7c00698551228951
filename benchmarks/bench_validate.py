"""Benchmark: `skinpipe validate` throughput on many assets, against plain stage opens.

    python benchmarks/bench_validate.py [--copies 100] [-o benchmarks/results/validate.json]

Validates N copies of the clean fixture asset with one validation context (USD's
built-in validators and skinpipe's rules), and, as the peer, only opens the same
stages with Usd.Stage.Open; reports seconds per asset and the ratio.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from pxr import Usd

from skinpipe.usd.validate import validate_files

CLEAN = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "usd" / "clean" / \
    "two_regions.usda"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--copies", type=int, default=100)
    parser.add_argument("-o", "--output", type=Path,
                        default=Path("benchmarks/results/validate.json"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i in range(args.copies):
            p = Path(tmp) / f"asset{i:03d}.usda"
            shutil.copy(CLEAN, p)
            paths.append(p)
        start = time.perf_counter()
        for p in paths:
            Usd.Stage.Open(str(p))
        open_s = time.perf_counter() - start
        start = time.perf_counter()
        reports = validate_files(paths)
        validate_s = time.perf_counter() - start
    assert all(not r.problems for r in reports)
    doc = {"benchmark": "validate", "assets": args.copies, "validate_seconds": validate_s,
           "open_only_seconds": open_s, "seconds_per_asset": validate_s / args.copies,
           "ratio_to_open": validate_s / open_s}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    each_ms = 1000 * validate_s / args.copies
    print(f"{args.copies} assets: validate {validate_s:.2f} s ({each_ms:.1f} ms each), "
          f"open only {open_s:.2f} s, ratio {validate_s / open_s:.1f}x")


if __name__ == "__main__":
    main()
