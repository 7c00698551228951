"""Benchmark: one 6-term, 3-channel fit of a 200-sample profile, against scipy's SLSQP.

Peers measured in the same run on the same profiles: the paper's GA + SQP (scipy
SLSQP standing in for MATLAB fmincon) and a 50-start IPOPT multi-start, whose best
objective is the reference optimum. Then, on the six sample regions (ingested from
skinpipe/samples/captures), skinpipe's fit against a baseline written here from scipy
alone (:func:`multistart_baseline`: a 20-start SLSQP on the log-variances, weights by
NNLS), both judged by :func:`objective_eq2c` (issue 23): skinpipe's fit by values alone,
the same objective, and beside it what the default fit (values and radial energy) gives
up of it. Writes JSON (comparable over time) and tables.

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
from scipy.optimize import minimize, nnls

from skinpipe.capture.ingest import IngestOptions, ingest_region, read_capture_set
from skinpipe.profile.fit import FitOptions, fit_multistart, fit_sum_of_gaussians
from skinpipe.profile.models import (
    dipole_profile,
    dipole_total_reflectance,
    ring_widths_mm,
    sum_of_gaussians,
)
from skinpipe.profile.reference_data import DEON_2007_SKIN, JENSEN_2001
from skinpipe.profile.types import MeasuredProfile

CAPTURES = Path(__file__).resolve().parent.parent / "skinpipe" / "samples" / "captures"


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


def _gaussians(r: np.ndarray, variances_mm2: np.ndarray) -> np.ndarray:
    """(n, k) normalised 2D Gaussians G(v, r) = e^(-r^2 / 2v) / (2 pi v)."""
    v = np.asarray(variances_mm2, dtype=np.float64)[None, :]
    return np.exp(-(r[:, None] ** 2) / (2.0 * v)) / (2.0 * np.pi * v)


def objective_eq2c(profile: MeasuredProfile, variances_mm2: np.ndarray,
                   weights: np.ndarray) -> float:
    """The judge: mean over R, G, B of sum r dr (p - f)^2 / sum r dr p^2 (eq. 2c's squared
    error, normalised by the measured profile), for weights (k, 3)."""
    r = profile.radius_mm
    a = r * ring_widths_mm(r)
    f = _gaussians(r, variances_mm2) @ np.asarray(weights, dtype=np.float64)
    p = profile.values
    return float(np.mean(np.sum(a[:, None] * (p - f) ** 2, axis=0)
                         / np.sum(a[:, None] * p**2, axis=0)))


def _simplex_weights(basis: np.ndarray, a: np.ndarray, p: np.ndarray) -> np.ndarray:
    """min sum a (p - B w)^2 over w >= 0, sum w = 1: NNLS with a heavy row for the sum."""
    sq = np.sqrt(a)[:, None]
    mat = basis * sq
    big = 1e4 * max(float(np.linalg.norm(mat)), 1.0)
    w, _ = nnls(np.vstack([mat, np.full((1, basis.shape[1]), big)]),
                np.concatenate([p * sq[:, 0], [big]]), maxiter=100 * basis.shape[1])
    return w / max(float(w.sum()), 1e-300)


def multistart_baseline(profile: MeasuredProfile, k: int = 6, starts: int = 20,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """The issue's peer: SLSQP on the k log-variances (bounds from half the smallest
    sample spacing to twice the largest radius), the weights of each channel solved
    exactly by NNLS for every trial, best of ``starts`` log-uniform starts. Returns the
    variances (mm^2), weights (k, 3) and seconds."""
    start_time = time.perf_counter()
    r, p = profile.radius_mm, profile.values
    a = r * ring_widths_mm(r)
    gaps = np.diff(r)
    lo = np.log((0.5 * min(gaps[gaps > 0].min(), r[r > 0].min())) ** 2)
    hi = np.log((2.0 * r.max()) ** 2)

    def weights_for(log_v: np.ndarray) -> np.ndarray:
        basis = _gaussians(r, np.exp(log_v))
        return np.stack([_simplex_weights(basis, a, p[:, c]) for c in range(3)], axis=1)

    def cost(log_v: np.ndarray) -> float:
        return objective_eq2c(profile, np.exp(log_v), weights_for(log_v))

    rng = np.random.default_rng(seed)
    best = (np.inf, np.zeros(k))
    for _ in range(starts):
        x0 = np.sort(rng.uniform(lo, hi, k))
        res = minimize(cost, x0, method="SLSQP", bounds=[(lo, hi)] * k,
                       options={"maxiter": 200, "ftol": 1e-12})
        value = cost(res.x)
        if value < best[0]:
            best = (value, res.x)
    log_v = best[1]
    return np.exp(log_v), weights_for(log_v), time.perf_counter() - start_time


def sample_regions() -> list[MeasuredProfile]:
    """The six sample regions' profiles, ingested at the defaults."""
    captures = read_capture_set(CAPTURES)
    return [ingest_region(captures, name, IngestOptions()).profile
            for name in captures.regions]


def regions_against_baseline(repeats: int) -> list[dict]:
    """Per sample region: skinpipe's fit by values alone (``energy_weight`` 0: eq. 2a, the
    baseline's objective; median seconds over ``repeats`` seeds, the worst objective over
    them) against :func:`multistart_baseline`, one judge; and the default fit's eq. 2c,
    which also fits the radial energy and so gives up some of eq. 2c for the light's
    placement (docs/fit.md)."""
    rows = []
    for prof in sample_regions():
        by_values = FitOptions(k=6, energy_weight=0.0)
        fit_sum_of_gaussians(prof, by_values)  # builds and caches the casadi solver
        seconds, objectives = [], []
        for seed in range(repeats):
            t0 = time.perf_counter()
            fit = fit_sum_of_gaussians(prof, FitOptions(**{**by_values.__dict__, "seed": seed}))
            seconds.append(time.perf_counter() - t0)
            objectives.append(objective_eq2c(prof, fit.variances_mm2, fit.weights))
        default = fit_sum_of_gaussians(prof, FitOptions(k=6))
        variances, weights, base_s = multistart_baseline(prof)
        base = objective_eq2c(prof, variances, weights)
        rows.append({"region": prof.name, "ours_median_s": statistics.median(seconds),
                     "ours_max_s": max(seconds), "ours_worst_objective": max(objectives),
                     "ours_best_objective": min(objectives), "baseline_objective": base,
                     "baseline_s": base_s, "objective_ratio": max(objectives) / base,
                     "speed_ratio": base_s / statistics.median(seconds),
                     "default_fit_objective_ratio": objective_eq2c(
                         prof, default.variances_mm2, default.weights) / base})
    return rows


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
    regions = regions_against_baseline(args.repeats)
    doc = {"benchmark": "fit", "k": 6, "channels": 3, "samples": 200, "repeats": args.repeats,
           "machine": {"python": platform.python_version(), "cpu": platform.processor(),
                       "cores": __import__("os").cpu_count()},
           "results": results, "sample_regions": regions}
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
    print(f"\n{'region':<10} {'ours med s':>10} {'ours max s':>10} {'worst obj':>10} "
          f"{'20-start obj':>12} {'obj ratio':>9} {'baseline s':>10} {'speed':>6} "
          f"{'default ratio':>13}")
    for r in regions:
        print(f"{r['region']:<10} {r['ours_median_s']:>10.3f} {r['ours_max_s']:>10.3f} "
              f"{r['ours_worst_objective']:>10.3e} {r['baseline_objective']:>12.3e} "
              f"{r['objective_ratio']:>9.4f} {r['baseline_s']:>10.2f} {r['speed_ratio']:>6.1f} "
              f"{r['default_fit_objective_ratio']:>13.3f}")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
