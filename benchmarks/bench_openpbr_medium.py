"""Benchmark: the OpenPBR medium of each region, traced, against the measured profile.

    python benchmarks/bench_openpbr_medium.py [-o benchmarks/results/openpbr_medium.json]

For the sample captures (through ``skinpipe ingest``; the level is the asset's default
albedo, as ``author`` makes it) and for the traced skin1 profile (tests/fixtures/physics,
its total reflectance as measured), the medium :func:`skinpipe.usd.openpbr.region_medium`
exports is traced by the independent light tracer (tests/physics/light_tracer.py, held
to Mitsuba 3's volpath by benchmarks/bench_mitsuba.py), pencil-lit, and its exit profile
compared with the measured one: the edge-spread error (largest difference beyond the
central two rings, share of the plateau) and the total reflectance, traced over
measured. The inversion's own model residual is printed beside them.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from skinpipe.package_data import package_folder  # noqa: E402
from skinpipe.profile.edge import edge_positions_mm, spread_beyond_rings  # noqa: E402
from skinpipe.profile.io import read_profile_csv  # noqa: E402
from skinpipe.profile.medium import estimate_medium  # noqa: E402
from skinpipe.profile.models import ring_edges_mm  # noqa: E402
from skinpipe.usd.author import DEFAULT_ALBEDO  # noqa: E402
from tests.physics.light_tracer import Medium, trace  # noqa: E402

PHOTONS = 200_000


def traced_against_measured(name: str, radius: np.ndarray, values: np.ndarray,
                            reflectance: np.ndarray) -> dict:
    start = time.perf_counter()
    medium = estimate_medium(radius, values, reflectance)
    seconds = time.perf_counter() - start
    outer = ring_edges_mm(radius)
    t = edge_positions_mm(radius)
    keep = np.abs(t) >= outer[1] - 1e-12
    edge, total = [], []
    for c in range(3):
        a, length = medium.single_scattering_albedo[c], medium.mean_free_path_mm[c]
        tally = trace(Medium(a / length, (1 - a) / length), PHOTONS, outer, seed=40 + c)
        measured = spread_beyond_rings(radius, values[:, c], t)
        traced = spread_beyond_rings(radius, tally.radiance(), t)
        traced *= measured[0] / traced[0]
        edge.append(round(float(np.abs(traced - measured)[keep].max() / measured[0]), 4))
        total.append(round(math.pi * tally.total / float(reflectance[c]), 4))
    row = {"profile": name, "model": medium.model,
           "single_scattering_albedo": medium.single_scattering_albedo.round(5).tolist(),
           "mean_free_path_mm": medium.mean_free_path_mm.round(4).tolist(),
           "subsurface_color": medium.subsurface_colour.round(4).tolist(),
           "model_edge_error": medium.edge_error.round(4).tolist(),
           "traced_edge_error": edge, "traced_over_measured_total": total,
           "inversion_seconds": round(seconds, 3)}
    print(f"{name:10s} {medium.model:7s} model edge {row['model_edge_error']}  traced edge "
          f"{edge}  total traced/measured {total}", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "results" /
                                                      "openpbr_medium.json"))
    args = parser.parse_args()
    rows = []
    fixtures = ROOT / "tests" / "fixtures" / "physics"
    data = np.loadtxt(fixtures / "skin1.csv", delimiter=",", skiprows=1)
    totals = json.loads((fixtures / "totals.json").read_text())["skin1"]["channels"]
    rows.append(traced_against_measured(
        "skin1", data[:, 0], data[:, 1:],
        np.array([math.pi * c["up_radiance_total"] for c in totals])))
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "skinpipe", "ingest",
                        str(package_folder("samples", "captures")), "-o", f"{tmp}/p"],
                       check=True, stdout=subprocess.DEVNULL)
        for csv in sorted(Path(tmp, "p").glob("*.csv")):
            profile = read_profile_csv(csv)
            rows.append(traced_against_measured(csv.stem, profile.radius_mm, profile.values,
                                                np.array(DEFAULT_ALBEDO)))
    out = Path(args.output)
    out.write_text(json.dumps({"photons_per_channel": PHOTONS, "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
