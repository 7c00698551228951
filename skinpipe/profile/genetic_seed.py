"""The genetic algorithm that seeds the fit (Park & Oh 2009, section 2.2): candidate
variance grids scored with their best weights, and the one-term moves that let a refined
fit hop to another basin."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .objective import Curve, grid_fitness
from .types import FloatArray

GA_MIN_LOG_SPACING = 0.2
"""Seeds keep neighbouring variances at least a factor e^0.4 (1.22) apart.

Two nearly equal variances are a saddle of the least-squares problem (the pair can
trade weight freely), where IPOPT spends a hundred iterations before escaping; the GA
therefore proposes spread grids and leaves fine placement to IPOPT."""


def _spread(pop: FloatArray, lo: float, hi: float) -> FloatArray:
    """Repair sorted rows so that neighbours are at least GA_MIN_LOG_SPACING apart."""
    k = pop.shape[1]
    gap = min(GA_MIN_LOG_SPACING, (hi - lo) / max(k, 1))
    steps = gap * np.arange(k)
    # Subtracting the ramp turns the spacing rule into plain monotonicity.
    flat = np.maximum.accumulate(pop - steps, axis=1)
    flat = np.minimum(flat, hi - steps[-1])
    return np.clip(flat + steps, lo, hi)



def genetic_seed(
    curves: Sequence[Curve],
    k: int,
    log_bounds: tuple[float, float],
    rng: np.random.Generator,
    generations: int,
    population: int,
    free_scale: bool,
) -> tuple[FloatArray, float]:
    """Genetic algorithm over sorted log-variances (Park & Oh 2009, section 2.2).

    Fitness is the objective with each candidate's best weights (a batched simplex
    solve), so the GA searches only the nonlinear part. Returns the best grid and its
    objective. Blend crossover, Gaussian mutation shrinking over the generations,
    tournament selection, two elites.
    """
    lo, hi = log_bounds
    span = hi - lo
    pop = _spread(np.sort(rng.uniform(lo, hi, size=(population, k)), axis=1), lo, hi)
    pop[0] = np.linspace(lo + 0.1 * span, hi - 0.1 * span, k) if k > 1 else 0.5 * (lo + hi)
    fit, _ = grid_fitness(pop, curves, free_scale)
    for gen in range(generations):
        order = np.argsort(fit)
        pop, fit = pop[order], fit[order]
        n_child = population - 2
        contenders = rng.integers(0, population, size=(2, n_child, 3))
        parents = np.min(contenders, axis=2)  # sorted by fitness: the smaller index wins
        alpha = rng.uniform(-0.25, 1.25, size=(n_child, k))
        child = alpha * pop[parents[0]] + (1.0 - alpha) * pop[parents[1]]
        sigma = span * (0.25 * (1.0 - gen / generations) + 0.01)
        mutate = rng.random((n_child, k)) < 0.3
        child = child + mutate * rng.normal(0.0, sigma, size=(n_child, k))
        child = _spread(np.sort(np.clip(child, lo, hi), axis=1), lo, hi)
        child_fit, _ = grid_fitness(child, curves, free_scale)
        pop = np.concatenate([pop[:2], child])
        fit = np.concatenate([fit[:2], child_fit])
    best = int(np.argmin(fit))
    return pop[best], float(fit[best])


SWAP_POSITIONS = 16
"""Log-spaced places across the variance bounds a term may move to in :func:`swap_terms`."""


def swap_terms(
    log_u: FloatArray,
    curves: Sequence[Curve],
    log_bounds: tuple[float, float],
    free_scale: bool,
    keep: int = 3,
) -> FloatArray:
    """Grids one term away from ``log_u``: each of the k terms moved to each of
    SWAP_POSITIONS places across the bounds that lie a factor e or more from every
    term (a new use for it, not a nudge the refinement makes anyway), all scored
    at once with their best weights (:func:`grid_fitness`); returns ``log_u`` and the
    ``keep`` best moves to distinct places.

    A refined fit sits in one basin; the optimum of a sum of Gaussians often differs
    from it by one term put to another use (the sample forehead: a term at 0.0003 mm^2
    for the core instead of one at 8 mm^2 for the tail, 26% lower objective). Moving one
    term at a time is the cheapest search that crosses between such basins (k x 16
    grids, the cost of three GA generations)."""
    lo, hi = log_bounds
    k = log_u.size
    places = np.linspace(lo, hi, SWAP_POSITIONS)
    moved = np.repeat(np.arange(k), places.size)
    place = np.tile(places, k)
    cand = np.repeat(log_u[None, :], moved.size, axis=0)
    cand[np.arange(moved.size), moved] = place
    new_use = np.abs(log_u[None, :] - place[:, None]).min(axis=1) >= 1.0
    cand, place = np.sort(cand[new_use], axis=1), place[new_use]
    if cand.shape[0] == 0:
        return log_u[None, :]
    obj, _ = grid_fitness(cand, curves, free_scale)
    picked, used = [log_u], []
    for i in np.argsort(obj):
        if len(picked) > keep:
            break
        if all(abs(place[i] - q) > 0.5 for q in used):
            picked.append(cand[i])
            used.append(place[i])
    return np.array(picked)
