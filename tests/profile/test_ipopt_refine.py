"""The fit's IPOPT refinement (skinpipe/profile/ipopt_refine.py): its Gauss-Newton
Hessian against finite differences of residuals computed here in numpy."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.profile.fit import _make_curves
from skinpipe.profile.ipopt_refine import HESS_REG, gauss_newton_problem, parameter_layout
from skinpipe.profile.models import sum_of_gaussians
from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.profile.types import MeasuredProfile


@pytest.mark.parametrize("fixed", [False, True])
def test_gauss_newton_hessian_is_2_jt_j_by_finite_differences(fixed: bool) -> None:
    """IPOPT's Hessian (built from Gram matrices shared by a sample set's curves) against
    2 J'J with J the finite-difference Jacobian of the weighted residuals sqrt(a) (q - G w)
    and of the energy residuals sqrt(b) (t - E w), computed here in numpy; two sample
    sets (one profile's channels sharing weights, one with per-channel standard
    deviations), so both groupings are covered."""
    rng = np.random.default_rng(11)
    r = np.linspace(0.0, 3.0, 40)
    values = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r)
    plain = MeasuredProfile(r, values)
    noisy = MeasuredProfile(r, values * 1.01, stddev=values * 0.02 + 1e-3)
    curves = (_make_curves([plain], [(0, c) for c in range(3)], 1.0)
              + _make_curves([noisy], [(0, 0), (0, 1)], 1.0, use_stddev=True))
    layout, chunks = parameter_layout(curves)
    assert [m for _, m in layout] == [3, 1, 1]
    k = 4
    log_u = np.log([0.01, 0.1, 0.7, 3.0])
    w = rng.uniform(0.1, 1.0, (len(curves), k))
    params = np.concatenate(chunks + ([log_u] if fixed else []))
    _, hess = gauss_newton_problem(layout, k, fixed, False)
    x = w.ravel() if fixed else np.concatenate([log_u, w.ravel()])
    ours = np.array(hess(x, params, 1.0, np.zeros(len(curves)))).reshape(x.size, x.size)

    def residuals(xv: np.ndarray) -> np.ndarray:
        lu = log_u if fixed else xv[:k]
        ww = (xv if fixed else xv[k:]).reshape(len(curves), k)
        v = np.exp(lu)
        out = []
        for cv, wc in zip(curves, ww, strict=True):
            g = np.exp(-(cv.rho[:, None] ** 2) / (2 * v)) / (2 * np.pi * v)
            e = 1 - np.exp(-(cv.rho_e[:, None] ** 2) / (2 * v))  # light within rho_e
            out += [np.sqrt(cv.a) * (cv.q - g @ wc), np.sqrt(cv.b) * (cv.t - e @ wc)]
        return np.concatenate(out)

    step = 1e-6
    jac = np.stack([(residuals(x + step * e) - residuals(x - step * e)) / (2 * step)
                    for e in np.eye(x.size)], axis=1)
    reference = np.triu(2 * jac.T @ jac + HESS_REG * np.eye(x.size))
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-6 * np.abs(reference).max())
