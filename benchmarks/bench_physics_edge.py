"""Benchmark: a hard shadow edge against light itself, both roads a profile takes.

    python benchmarks/bench_physics_edge.py [-o benchmarks/results/physics_edge.json]

For the light tracer's media (tests/fixtures/physics: skin1 index-matched and at eta
1.4, a forward-scattering medium with g = 0.8, marble), the profile as a CSV through
``skinpipe fit`` at its defaults, and as a simulated pencil capture through ``skinpipe
ingest`` + ``fit``, then ``author`` and ``render`` of a flat slab under a hard shadow
edge (tests/render/test_physics_edge.py). Printed per channel as ratios against the
peer, the traced edge: 10-90% width, light in the shadow, and the largest difference
as a share of the plateau. Also the fit by values alone (--energy-weight 0) on skin1,
with the edge error its FIT.json reports beside the rendered one.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.render.test_physics_edge import edge_against_truth  # noqa: E402

MEDIA = ("skin1", "skin1_eta1.4", "forward", "marble")


def _row(tmp: Path, medium: str, road: str, *fit_args: str) -> dict:
    start = time.perf_counter()
    report = edge_against_truth(tmp, medium, road, *fit_args)
    fit = json.loads((tmp / "fits" / f"{medium}.json").read_text())
    rendered, traced = report["width_mm"]
    row = {"medium": medium, "road": road, "fit_args": list(fit_args),
           "width_rendered_mm": rendered, "width_traced_mm": traced,
           "width_ratio": [round(a / b, 3) for a, b in zip(rendered, traced, strict=True)],
           "shadow_light_ratio": report["shadow_light"],
           "edge_error_of_plateau": report["edge_error"],
           "fit_reported_edge_error": [round(v, 4) for v in fit["edge"]["edge_error"]],
           "fit_reported_eq2c": [round(v, 5) for v in fit["error"]],
           "seconds": round(time.perf_counter() - start, 1)}
    print(f"{medium:>13} {road:>7} {' '.join(fit_args):>18}: width/traced "
          f"{row['width_ratio']}, shadow light/traced {row['shadow_light_ratio']}, "
          f"edge error {row['edge_error_of_plateau']} (fit reports "
          f"{row['fit_reported_edge_error']}, eq. 2c {row['fit_reported_eq2c']})", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", type=Path,
                        default=ROOT / "benchmarks" / "results" / "physics_edge.json")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (medium, road, fit_args) in enumerate(
                [(m, r, ()) for m in MEDIA for r in ("csv", "capture")]
                + [("skin1", "csv", ("--energy-weight", "0"))]):
            folder = Path(tmp) / str(i)
            folder.mkdir()
            rows.append(_row(folder, medium, road, *fit_args))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"benchmark": "physics_edge", "rows": rows},
                                      indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
