"""Benchmark: one 6-term, 3-channel fit of a 200-sample profile, against scipy's SLSQP.

Peers measured in the same run on the same profiles: the paper's GA + SQP (scipy
SLSQP standing in for MATLAB fmincon) and a 50-start IPOPT multi-start, whose best
objective is the reference optimum. Writes JSON (comparable over time) and a table.

    python benchmarks/bench_fit.py [--repeats 11] [-o benchmarks/results/fit.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from pipeline.profile.fit import FitOptions, MeasuredProfile, fit_multistart, fit_sum_of_gaussians
from pipeline.profile.models import dipole_profile, dipole_total_reflectance, sum_of_gaussians
from pipeline.profile.reference_data import DEON_2007_SKIN, JENSEN_2001


def profiles() -> list[MeasuredProfile]:
    r = np.linspace(0.0, 4.0, 200)
    rng = np.random.default_rng(0)
    out = []
    for name in ("skin1", "skin2"):
        c = JENSEN_2001[name]
        clean = dipole_profile(r, c) / dipole_total_reflectance(c)
        out.append(MeasuredProfile(r, clean * (1 + 0.01 * rng.standard_normal(clean.shape)),
                                   name=f"dipole_{name}_1pct"))
    deon = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r)
    out.append(MeasuredProfile(r, deon, name="deon2007"))
    return out


def timed(profile: MeasuredProfile, options: FitOptions, repeats: int) -> dict:
    fit_sum_of_gaussians(profile, options)  # builds and caches the casadi solver
    seconds, objectives, errors = [], [], []
    for seed in range(repeats):
        start = time.perf_counter()
        fit = fit_sum_of_gaussians(profile, FitOptions(**{**options.__dict__, "seed": seed}))
        seconds.append(time.perf_counter() - start)
        objectives.append(fit.objective)
        errors.append(float(fit.error.max()))
    return {"median_s": statistics.median(seconds), "max_s": max(seconds),
            "objectives": objectives, "median_error": statistics.median(errors)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=11)
    parser.add_argument("-o", "--output", type=Path, default=Path("benchmarks/results/fit.json"))
    args = parser.parse_args()
    results = []
    for prof in profiles():
        best = fit_multistart(prof, FitOptions(k=6), starts=50)
        ours = timed(prof, FitOptions(k=6), args.repeats)
        peer = timed(prof, FitOptions(k=6, solver="slsqp"), args.repeats)
        for entry in (ours, peer):
            entry["hits_multistart_optimum"] = int(sum(
                o <= best.objective * (1 + 1e-3) or o < 1e-9 for o in entry["objectives"]))
            del entry["objectives"]
        results.append({"profile": prof.name, "multistart_objective": best.objective,
                        "multistart_seconds": best.seconds, "ga_ipopt": ours, "ga_slsqp": peer,
                        "speedup_vs_slsqp": peer["median_s"] / ours["median_s"]})
    doc = {"benchmark": "fit", "k": 6, "channels": 3, "samples": 200, "repeats": args.repeats,
           "machine": {"python": platform.python_version(), "cpu": platform.processor(),
                       "cores": __import__("os").cpu_count()},
           "results": results}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"{'profile':<20} {'ours med s':>10} {'slsqp med s':>11} {'ratio':>6} "
          f"{'hits ours':>9} {'hits slsqp':>10} {'err ours':>9}")
    for r in results:
        print(f"{r['profile']:<20} {r['ga_ipopt']['median_s']:>10.3f} "
              f"{r['ga_slsqp']['median_s']:>11.3f} {r['speedup_vs_slsqp']:>6.2f} "
              f"{r['ga_ipopt']['hits_multistart_optimum']:>6}/{args.repeats:<2} "
              f"{r['ga_slsqp']['hits_multistart_optimum']:>7}/{args.repeats:<2} "
              f"{r['ga_ipopt']['median_error']:>9.2e}")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
