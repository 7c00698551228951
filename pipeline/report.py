"""Error against run time: each stage's trade-off measured in one run (JSON + PNG)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .fileio import atomic_path, atomic_write_json
from .fit import FitOptions, MeasuredProfile, fit_sum_of_gaussians

FIT_METHODS: dict[str, dict[str, Any]] = {
    "ga+ipopt": {"init": "ga", "solver": "ipopt"},
    "naive+ipopt": {"init": "naive", "solver": "ipopt"},
    "ga+slsqp": {"init": "ga", "solver": "slsqp"},
}
"""The default (GA seed + IPOPT), IPOPT from a log-spaced start, and the paper's
GA + SQP with scipy's SLSQP standing in for MATLAB's fmincon."""


@dataclass
class TradeoffRow:
    profile: str
    method: str
    k: int
    seconds: float
    error_max: float
    error: list[float]
    objective: float
    status: str


def fit_tradeoff(
    profiles: Sequence[MeasuredProfile],
    ks: Sequence[int] = tuple(range(1, 9)),
    methods: Sequence[str] = tuple(FIT_METHODS),
    seed: int = 0,
    progress: Any = None,
) -> list[TradeoffRow]:
    """Fit every profile with every k and method; wall seconds and eq. 2c error per fit."""
    rows = []
    for prof in profiles:
        for method in methods:
            for k in ks:
                start = time.perf_counter()
                fit = fit_sum_of_gaussians(prof, FitOptions(k=k, seed=seed, **FIT_METHODS[method]))
                seconds = time.perf_counter() - start
                rows.append(TradeoffRow(prof.name, method, k, seconds, float(fit.error.max()),
                                        [float(e) for e in fit.error], fit.objective, fit.status))
                if progress is not None:
                    progress(f"{prof.name} {method} k={k}: error {fit.error.max():.2e}, "
                             f"{seconds:.2f} s")
    return rows


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated in (seconds, error), both minimised (per profile)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], np.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def write_fit_report(rows: Sequence[TradeoffRow], out_dir: Path, default_k: int = 6) -> dict:
    """fit_tradeoff.json and fit_tradeoff.png (error vs seconds, log axes) in ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    front: set[int] = set()
    for prof in {r.profile for r in rows}:
        idx = [i for i, r in enumerate(rows) if r.profile == prof]
        front.update(idx[j] for j in pareto_front([(rows[i].seconds, rows[i].error_max)
                                                   for i in idx]))
    default_rows = [i for i, r in enumerate(rows) if r.method == "ga+ipopt" and r.k == default_k]
    doc = {
        "stage": "fit",
        "error_measure": "max over channels of eq. 2c (Park & Oh 2009)",
        "rows": [r.__dict__ | {"pareto": i in front} for i, r in enumerate(rows)],
        "default": {"method": "ga+ipopt", "k": default_k,
                    "on_pareto_front": [i in front for i in default_rows]},
    }
    atomic_write_json(out_dir / "fit_tradeoff.json", doc)
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    markers = {"ga+ipopt": "o", "naive+ipopt": "s", "ga+slsqp": "^"}
    for prof in sorted({r.profile for r in rows}):
        for method in sorted({r.method for r in rows}):
            sel = [r for r in rows if r.profile == prof and r.method == method]
            ax.plot([r.seconds for r in sel], [max(r.error_max, 1e-8) for r in sel],
                    marker=markers.get(method, "x"), linestyle="-", alpha=0.8,
                    label=f"{prof} {method}")
            for r in sel:
                ax.annotate(str(r.k), (r.seconds, max(r.error_max, 1e-8)), fontsize=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per fit (s)")
    ax.set_ylabel("eq. 2c error (max over R, G, B)")
    ax.set_title("Fit: error against run time (labels: k)")
    ax.legend(fontsize=6)
    ax.grid(True, which="both", alpha=0.3)
    with atomic_path(out_dir / "fit_tradeoff.png") as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return doc
