"""Weights of a sum of Gaussians over the simplex (w >= 0, sum w = 1; or w >= 0 alone
for a free scale): the exact least-squares weights for a fixed variance grid, as the
fit's genetic algorithm scores every candidate grid and as the refinement polishes its
result (Park & Oh 2009, eq. 2b)."""

from __future__ import annotations

import numpy as np

from .types import FloatArray

GRAM_PIVOT_ROUNDS = 8
"""Exchange rounds :func:`gram_weights_pivoting` tries before it leaves a system to
Lawson-Hanson (measured on the six sample regions' fits: 1 system in 16,821 needed more
than 8; 295 more than 4)."""


def gram_weights_pivoting(
    hess: FloatArray, grad: FloatArray, free_scale: bool, rounds: int = GRAM_PIVOT_ROUNDS
) -> tuple[FloatArray, np.ndarray]:
    """min w'Hw - 2 g'w over the simplex (or w >= 0) for a batch of small systems, by
    block principal pivoting (Portugal, Judice & Vicente 1994; Kim & Park 2011, alg. 2).

    Each round solves, for every system at once, the KKT equations on its current free
    set, H_FF w_F + mu 1 = g_F (1'w_F = 1 unless ``free_scale``), then moves every
    infeasible variable across: free ones with w < 0 out, bound ones whose multiplier
    (Hw - g + mu)_i is negative in. A system whose solution satisfies all KKT conditions
    is exactly optimal (the problem is convex). Returns the weights (rows of systems
    left unsettled after ``rounds`` are NaN) and the indices of those systems: the caller
    hands them to Lawson-Hanson, which always terminates (Kim & Park's backup rule,
    replaced by a solver that cannot cycle).
    """
    batch, k = grad.shape
    n = k if free_scale else k + 1
    scale = np.trace(hess, axis1=-2, axis2=-1)
    h = hess + 1e-12 * scale[:, None, None] * np.eye(k)
    kkt = np.zeros((batch, n, n))
    kkt[:, :k, :k] = h
    rhs = np.zeros((batch, n))
    rhs[:, :k] = grad
    if not free_scale:
        kkt[:, k, :k] = kkt[:, :k, k] = rhs[:, k] = 1.0
    # Relative to each system's scale: round-off must not flip a variable back and forth.
    tol_w = 1e-13
    tol_mult = 1e-10 * np.maximum(np.abs(grad).max(axis=1), 1e-300)
    free = np.ones((batch, k), dtype=bool)
    out = np.full((batch, k), np.nan)
    # A Gram matrix of Gaussians that underflow at every sample is zero: any weights
    # do, and Lawson-Hanson picks one; the KKT matrix would be singular.
    solvable = np.isfinite(scale) & (scale > 0)
    todo, lawson_hanson = np.flatnonzero(solvable), np.flatnonzero(~solvable)
    for _ in range(rounds):
        if todo.size == 0:
            break
        bound = ~free[todo]
        rows = np.zeros((todo.size, n), dtype=bool)
        rows[:, :k] = bound
        # A bound variable's row becomes w_i = 0; its column then multiplies zero.
        m = np.where(rows[:, :, None], np.eye(n), kkt[todo])
        if not free_scale:
            m[:, :k, k] = ~bound
        try:
            sol = np.linalg.solve(m, np.where(rows, 0.0, rhs[todo])[..., None])[..., 0]
        except np.linalg.LinAlgError:  # an exactly singular free block: NNLS decides
            break
        w = sol[:, :k]
        mult = np.einsum("bij,bj->bi", h[todo], w) - grad[todo]
        if not free_scale:
            mult += sol[:, k:]
        flip = (~bound & (w < -tol_w)) | (bound & (mult < -tol_mult[todo, None]))
        settled = ~flip.any(axis=1) & np.isfinite(sol).all(axis=1)
        out[todo[settled]] = np.where(bound[settled], 0.0, np.maximum(w[settled], 0.0))
        nxt = ~bound ^ flip
        if not free_scale:
            # The simplex needs a free variable: a system that would free none keeps its
            # set and is left to NNLS when the rounds run out.
            none_free = ~nxt.any(axis=1)
            nxt[none_free] = ~bound[none_free]
        free[todo] = nxt
        todo = todo[~settled]
    return out, np.concatenate([lawson_hanson, todo])


def gram_weights_nnls(hess: FloatArray, grad: FloatArray, free_scale: bool) -> FloatArray:
    """The same problem as :func:`gram_weights_pivoting` by Lawson-Hanson, one system at
    a time (scipy's NNLS): with H = R'R (Cholesky, jittered for near-equal variances) it
    is the k x k least-squares problem |R w - R^-T g|, with, unless ``free_scale``, a
    heavily weighted row for sum w = 1."""
    batch, k = grad.shape
    jitter = 1e-12 * np.trace(hess, axis1=-2, axis2=-1)[:, None, None] * np.eye(k)
    chol = np.linalg.cholesky(hess + jitter + 1e-300 * np.eye(k))
    rhs = np.linalg.solve(chol, grad[..., None])[..., 0]  # R^-T g with R = chol^T
    a_all = np.swapaxes(chol, -1, -2)
    if not free_scale:
        big = 1e3 * np.maximum(np.abs(a_all).max(axis=(1, 2)), 1.0)
        a_all = np.concatenate([a_all, np.repeat(big[:, None, None], k, axis=2)], axis=1)
        rhs = np.concatenate([rhs, big[:, None]], axis=1)
    from scipy.optimize import nnls  # lazy: 0.50 s to import

    out = np.empty_like(grad)
    for b in range(batch):
        out[b], _ = nnls(a_all[b], rhs[b], maxiter=50 * k)
    return out


def gram_weights(hess: FloatArray, grad: FloatArray, free_scale: bool) -> FloatArray:
    """Exact min w'Hw - 2 g'w over the simplex (or w >= 0) for a batch of small systems.

    Cost is independent of the number of samples, which is what makes the GA's fitness
    cheap. Block principal pivoting settles the batch together (3.3x faster than NNLS
    one system at a time over the 392 batches of one fit of each sample region); the
    few it leaves go to NNLS.
    """
    out, left = gram_weights_pivoting(hess, grad, free_scale)
    if left.size:
        out[left] = gram_weights_nnls(hess[left], grad[left], free_scale)
    if not free_scale:
        out /= np.maximum(out.sum(axis=1, keepdims=True), 1e-300)
    return out


def simplex_least_squares(
    basis: FloatArray, target: FloatArray, sample_weight: FloatArray, free_scale: bool = False
) -> FloatArray:
    """Exact min sum a (target - B w)^2 with w >= 0 and, unless free_scale, sum w = 1
    (several residuals: their rows stacked).

    Lawson-Hanson NNLS on the system augmented by a heavily weighted row sum w = 1.
    """
    sq = np.sqrt(sample_weight)
    a_mat = basis * sq[:, None]
    b_vec = target * sq
    if not free_scale:
        big = 1e4 * max(float(np.linalg.norm(a_mat)), 1.0)
        a_mat = np.vstack([a_mat, np.full((1, basis.shape[1]), big)])
        b_vec = np.concatenate([b_vec, [big]])
    from scipy.optimize import nnls  # lazy: 0.50 s to import

    w, _ = nnls(a_mat, b_vec, maxiter=50 * basis.shape[1])
    if not free_scale and w.sum() > 0:
        w = w / w.sum()
    return w
