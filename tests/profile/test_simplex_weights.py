"""The fit's weights over the simplex (skinpipe/profile/simplex_weights.py): block
principal pivoting against scipy's NNLS (Lawson-Hanson) on Gram systems of random sums
of Gaussians, and what it leaves to NNLS."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.profile.models import ring_widths_mm, sum_of_gaussians
from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.profile.simplex_weights import gram_weights, gram_weights_pivoting


def _gram_systems(n_systems: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Gram systems H = B'AB, g = B'Aq of random sums of Gaussians over radii (what the
    GA's fitness solves), with variances as close as 1.05x so that some are stiff."""
    rng = np.random.default_rng(seed)
    r = np.linspace(0.0, 4.0, 160)
    a = r * ring_widths_mm(r)
    log_v = np.sort(rng.uniform(np.log(1e-3), np.log(20.0), size=(n_systems, k)), axis=1)
    log_v[: n_systems // 4, 1] = log_v[: n_systems // 4, 0] + 0.05
    v = np.exp(log_v)[:, None, :]
    basis = np.exp(-(r[None, :, None] ** 2) / (2 * v)) / (2 * np.pi * v)
    truth = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r)[:, 0]
    q = truth * (1 + 0.05 * rng.standard_normal((n_systems, r.size)))
    hess = np.einsum("bnk,n,bnl->bkl", basis, a, basis)
    grad = np.einsum("bnk,n,bn->bk", basis, a, q)
    return hess, grad


def _quadratic(hess: np.ndarray, grad: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.einsum("bk,bkl,bl->b", w, hess, w) - 2 * np.einsum("bk,bk->b", w, grad)


@pytest.mark.parametrize("free_scale", [False, True])
def test_pivoting_weights_match_lawson_hanson(free_scale: bool) -> None:
    """Block principal pivoting against scipy's NNLS (Lawson-Hanson), system by system:
    same minimum of w'Hw - 2g'w on the simplex (or w >= 0), and the KKT conditions hold
    (w >= 0, multipliers of the zero weights >= 0, stationarity on the others)."""
    from scipy.optimize import nnls

    hess, grad = _gram_systems(400, 6, seed=3)
    w, left = gram_weights_pivoting(hess, grad, free_scale)
    settled = np.setdiff1d(np.arange(len(grad)), left)
    assert settled.size >= 0.95 * len(grad)
    w = w[settled]
    h, g = hess[settled], grad[settled]
    reference = np.empty_like(w)
    for i in range(len(settled)):
        chol = np.linalg.cholesky(h[i] + 1e-12 * np.trace(h[i]) * np.eye(6))
        mat, rhs = chol.T, np.linalg.solve(chol, g[i])
        if not free_scale:  # sum w = 1 as a heavily weighted row
            big = 1e3 * max(np.abs(mat).max(), 1.0)
            mat, rhs = np.vstack([mat, np.full((1, 6), big)]), np.append(rhs, big)
        reference[i] = nnls(mat, rhs, maxiter=600)[0]
    if not free_scale:
        reference /= reference.sum(axis=1, keepdims=True)
        np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    ours, theirs = _quadratic(h, g, w), _quadratic(h, g, reference)
    scale = np.abs(theirs) + np.einsum("bk,bk->b", np.abs(g), np.abs(reference))
    assert np.all(ours <= theirs + 1e-9 * scale), np.max((ours - theirs) / scale)
    assert np.all(w >= 0)
    gradient = np.einsum("bkl,bl->bk", h, w) - g
    free = w > 0
    mu = 0.0 if free_scale else -np.sum(np.where(free, gradient, 0), axis=1, keepdims=True) \
        / np.maximum(free.sum(axis=1, keepdims=True), 1)
    tol = 1e-6 * np.abs(g).max(axis=1, keepdims=True)
    assert np.all(np.abs(np.where(free, gradient + mu, 0)) <= tol)
    assert np.all(np.where(free, 0, gradient + mu) >= -tol)


def test_pivoting_leaves_what_it_cannot_settle_to_lawson_hanson() -> None:
    """A Gram matrix of zeros (Gaussians that underflow at every sample) and a system
    after zero rounds come back as unsettled, so the caller's NNLS answers them; the
    fitness' weights are then still on the simplex."""
    hess, grad = _gram_systems(8, 4, seed=5)
    hess[2], grad[2] = 0.0, 0.0
    _, left = gram_weights_pivoting(hess, grad, False)
    assert 2 in left
    _, none_done = gram_weights_pivoting(hess, grad, False, rounds=0)
    assert sorted(none_done) == list(range(8))
    w = gram_weights(hess, grad, False)
    assert np.all(np.isfinite(w)) and np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
