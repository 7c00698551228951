"""The fit's refinement: log-variances and weights together by casadi's IPOPT on the
Gauss-Newton Hessian (or scipy's SLSQP, the paper's SQP, for comparison), then the
weights solved exactly for the final grid and near-equal terms merged."""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from ..interrupts import raise_if_interrupted
from .objective import Curve, objective, polish_weights
from .types import FloatArray

HESS_REG = 1e-8
"""Levenberg term added to the Gauss-Newton Hessian: keeps it regular where a term's
weight is zero in every channel (its variance is then unidentifiable)."""
IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0,
    "sb": "yes",
    # 1e-6 took 27% fewer iterations (median 67.5 -> 49.5 a fit on the sample regions)
    # but left objectives up to 3.4e-6 above the 20-start baseline's where both find the
    # same optimum; refining only the kept solution to 1e-8 took as many iterations back.
    "tol": 1e-8,
    "acceptable_tol": 1e-7,
    "max_iter": 500,
    "mu_strategy": "adaptive",
    # The GA seed is good: start IPOPT at it rather than pushed into the interior.
    "warm_start_init_point": "yes",
    "warm_start_bound_push": 1e-9,
    "warm_start_bound_frac": 1e-9,
    "warm_start_mult_bound_push": 1e-9,
    "mu_init": 1e-6,
}


def _upper_gram(left: Any, right: Any, symmetric: bool) -> Any:
    """left' right for (n, k) SX matrices; only the upper triangle when the product is
    symmetric (the lower one is never read: IPOPT takes the Hessian's upper triangle)."""
    k = left.shape[1]
    out = ca.SX.zeros(k, k)
    for i in range(k):
        for j in range(i if symmetric else 0, k):
            out[i, j] = ca.dot(left[:, i], right[:, j])
    return out


def gauss_newton_problem(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> tuple[dict[str, Any], Any]:
    """The NLP (casadi dict) and its Gauss-Newton Lagrangian Hessian (a casadi Function
    of x, p, lam_f, lam_g giving the upper triangle) for one group's data layout.

    ``layout`` lists, per sample set, (samples, curves using it): curves of one sample
    set share their radii and, up to a factor, their sample weights a = s_c a_unit and
    energy weights b = e_c b_unit (:class:`Curve`). Decision variables are
    [log-variances (k, unless fixed), weights (k per curve)]; parameters are, per sample
    set, [rho, a_unit, rho_e, b_unit, then q, s_c, t, e_c of each curve], then fixed
    log-variances if any.

    The objective is a weighted sum of squares of two residuals, the values' q - G w and
    the energy's t - E w (E = 1 - exp(-rho_e^2 / 2u), :func:`energy_basis`), so the Lagrangian
    Hessian given to IPOPT is the Gauss-Newton one, 2 J' diag(a, b) J (the constraints
    are linear): exact at a zero-residual fit, always positive semi-definite, and an
    order of magnitude cheaper than the full second derivative. Its blocks come from
    k x k Gram matrices per sample set and residual, with D = dG/dlog u (or dE/dlog u):
    2 sum_c s_c (D'AD o w_c w_c') for the log-variances, 2 s_c diag(w_c) D'AB between
    them and curve c's weights, 2 s_c B'AB for those weights, and the same with b, E.
    """
    n_total = sum(n * (4 + 2 * m) + 2 * m for n, m in layout)
    n_curves = sum(m for _, m in layout)
    log_u = ca.SX.sym("log_u", k)
    w = ca.SX.sym("w", k * n_curves)
    params = ca.SX.sym("p", n_total + (k if fixed else 0))
    log_v = params[n_total:] if fixed else log_u
    u = ca.exp(log_v).T
    objective, constraints = 0, []
    n_x = k * n_curves + (0 if fixed else k)
    hess = ca.SX.zeros(n_x, n_x)
    w0 = 0 if fixed else k  # where the weights start in x
    offset, ci = 0, 0
    for n, m in layout:
        rho = params[offset : offset + n]
        a_unit = params[offset + n : offset + 2 * n]
        rho_e = params[offset + 2 * n : offset + 3 * n]
        b_unit = params[offset + 3 * n : offset + 4 * n]
        offset += 4 * n
        uu = ca.repmat(u, n, 1)
        half_rho2 = ca.repmat(rho**2, 1, k) / 2
        basis = ca.exp(-half_rho2 / uu) / (2 * math.pi * uu)
        half_e2 = ca.repmat(rho_e**2, 1, k) / 2
        outside = ca.exp(-half_e2 / uu)
        edge = 1 - outside
        grams = []
        for g, d_g, unit in (
                (basis, basis * (half_rho2 / uu - 1.0), a_unit),  # dG/dlog u
                (edge, -outside * half_e2 / uu, b_unit)):  # dE/dlog u
            weighted = g * ca.repmat(unit, 1, k)
            grams.append((_upper_gram(g, weighted, True),
                          None if fixed else _upper_gram(d_g, weighted, False),
                          None if fixed else _upper_gram(d_g, d_g * ca.repmat(unit, 1, k),
                                                         True)))
        for _ in range(m):
            q = params[offset : offset + n]
            scale = params[offset + n]
            t = params[offset + n + 1 : offset + 2 * n + 1]
            edge_scale = params[offset + 2 * n + 1]
            offset += 2 * n + 2
            wc = w[ci * k : (ci + 1) * k]
            resid = q - ca.mtimes(basis, wc)
            resid_edge = t - ca.mtimes(edge, wc)
            objective += scale * ca.dot(a_unit, resid * resid) \
                + edge_scale * ca.dot(b_unit, resid_edge * resid_edge)
            constraints.append(ca.sum1(wc))
            at = w0 + ci * k
            for sc, (gram_bb, gram_db, gram_dd) in zip((scale, edge_scale), grams,
                                                       strict=True):
                hess[at : at + k, at : at + k] += 2 * sc * gram_bb
                if not fixed:
                    hess[:k, :k] += 2 * sc * gram_dd * ca.mtimes(wc, wc.T)
                    hess[:k, at : at + k] += 2 * sc * ca.mtimes(ca.diag(wc), gram_db)
            ci += 1
    x = w if fixed else ca.vertcat(log_u, w)
    lam_f = ca.SX.sym("lam_f")
    lam_g = ca.SX.sym("lam_g", 0 if free_scale else n_curves)
    hess_fn = ca.Function(
        "gauss_newton_hess", [x, params, lam_f, lam_g],
        [ca.triu(lam_f * (hess + HESS_REG * ca.SX.eye(n_x)))],
        ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"],
    )
    nlp = {"x": x, "p": params, "f": objective}
    if not free_scale:
        nlp["g"] = ca.vertcat(*constraints)
    return nlp, hess_fn


def build_ipopt_solver(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> Any:
    """A casadi IPOPT solver for one group's data layout (:func:`gauss_newton_problem`):
    0.25 s to build, then reused for every profile of that layout."""
    nlp, hess = gauss_newton_problem(layout, k, fixed, free_scale)
    opts = {
        "print_time": False,
        "error_on_fail": True,
        "hess_lag": hess,
        "ipopt": dict(IPOPT_OPTIONS),
    }
    return ca.nlpsol("skin_fit", "ipopt", nlp, opts)


_THREAD_SOLVERS = threading.local()
SOLVERS_PER_THREAD = 64
"""Layouts a thread keeps solvers for (a batch of one face's regions has one or two)."""


def ipopt_solver(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> Any:
    """The calling thread's IPOPT solver for this layout (:func:`build_ipopt_solver`).

    One per thread: one casadi solver called from two threads at once crashes the
    interpreter (its evaluation buffers are shared), while solvers of their own run side
    by side: casadi lets go of the GIL and IPOPT (>= 3.14) calls MUMPS, which is not
    thread-safe, under its own lock."""
    cache: dict[tuple[Any, ...], Any] | None = getattr(_THREAD_SOLVERS, "cache", None)
    if cache is None:
        cache = _THREAD_SOLVERS.cache = {}
    key = (layout, k, fixed, free_scale)
    if key not in cache:
        if len(cache) >= SOLVERS_PER_THREAD:
            cache.clear()
        cache[key] = build_ipopt_solver(layout, k, fixed, free_scale)
    return cache[key]


def has_ipopt_solver(key: tuple[Any, ...]) -> bool:
    """Whether the calling thread has built its solver for ``key`` (:func:`ipopt_solver`'s
    arguments)."""
    return key in getattr(_THREAD_SOLVERS, "cache", {})


@dataclass
class GroupSolution:
    log_u: FloatArray
    weights: FloatArray  # (C, k)
    objective: float
    status: str
    iterations: int
    solver: str


def parameter_layout(curves: Sequence[Curve]
                     ) -> tuple[tuple[tuple[int, int], ...], list[FloatArray]]:
    """Group consecutive curves that share radii and unit sample weights; return the
    layout and the parameter chunks (:func:`ipopt_solver`)."""
    layout: list[tuple[int, int]] = []
    chunks: list[FloatArray] = []
    last: tuple[FloatArray, FloatArray, FloatArray] | None = None
    for cv in curves:
        if last is None or cv.rho is not last[0] or cv.a_unit is not last[1] \
                or cv.b_unit is not last[2]:
            layout.append((cv.rho.size, 0))
            chunks.extend([cv.rho, cv.a_unit, cv.rho_e, cv.b_unit])
            last = (cv.rho, cv.a_unit, cv.b_unit)
        layout[-1] = (layout[-1][0], layout[-1][1] + 1)
        chunks.extend([cv.q, np.array([cv.a_scale]), cv.t, np.array([cv.b_scale])])
    return tuple(layout), chunks


def refine_ipopt(
    curves: Sequence[Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    fixed: bool,
    free_scale: bool,
) -> GroupSolution:
    k = log_u0.size
    layout, chunks = parameter_layout(curves)
    solver = ipopt_solver(layout, k, fixed, free_scale)
    params = np.concatenate(chunks)
    w_hi = np.inf if free_scale else 1.0
    if fixed:
        params = np.concatenate([params, log_u0])
        x0, lbx, ubx = w0.reshape(-1), np.zeros(w0.size), np.full(w0.size, w_hi)
    else:
        x0 = np.concatenate([log_u0, w0.reshape(-1)])
        lbx = np.concatenate([np.full(k, log_bounds[0]), np.zeros(w0.size)])
        ubx = np.concatenate([np.full(k, log_bounds[1]), np.full(w0.size, w_hi)])
    kwargs: dict[str, Any] = {"x0": x0, "p": params, "lbx": lbx, "ubx": ubx}
    if not free_scale:
        kwargs["lbg"] = kwargs["ubg"] = np.ones(len(curves))
    try:
        sol = solver(**kwargs)
        x = np.asarray(sol["x"]).reshape(-1)
    except RuntimeError:
        x = None  # error_on_fail: the status below says why
    # casadi's callbacks catch a KeyboardInterrupt as IPOPT's NonIpopt_Exception_Thrown
    raise_if_interrupted()
    stats = solver.stats()
    status = str(stats.get("return_status", "unknown"))
    iterations = int(stats.get("iter_count", 0))
    if x is None or not np.all(np.isfinite(x)):
        start_obj = objective(log_u0, w0, curves)
        return GroupSolution(log_u0, w0, start_obj, status, iterations, "ipopt")
    log_u = log_u0 if fixed else x[:k]
    w = np.clip(x[k:] if not fixed else x, 0.0, None).reshape(len(curves), k)
    if not free_scale:
        w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    return GroupSolution(log_u, w, objective(log_u, w, curves), status, iterations, "ipopt")


def refine_slsqp(
    curves: Sequence[Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    free_scale: bool,
) -> GroupSolution:
    """scipy's SLSQP on the same problem: the paper's SQP (MATLAB fmincon), for comparison."""
    k, n_c = log_u0.size, len(curves)

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return x[:k], x[k:].reshape(n_c, k)

    def fun(x: FloatArray) -> float:
        lu, w = unpack(x)
        return objective(lu, w, curves)

    cons = [] if free_scale else [
        {"type": "eq", "fun": (lambda x, c=c: np.sum(unpack(x)[1][c]) - 1.0)} for c in range(n_c)
    ]
    from scipy.optimize import minimize  # lazy: 0.50 s to import

    bounds = [log_bounds] * k + [(0.0, None if free_scale else 1.0)] * (n_c * k)
    res = minimize(
        fun, np.concatenate([log_u0, w0.reshape(-1)]), method="SLSQP", bounds=bounds,
        constraints=cons, options={"maxiter": 500, "ftol": 1e-14},
    )
    lu, w = unpack(np.asarray(res.x))
    w = np.clip(w, 0.0, None)
    if not free_scale:
        w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    return GroupSolution(lu, w, objective(lu, w, curves), str(res.message), int(res.nit), "slsqp")


def with_exact_weights(
    sol: GroupSolution, curves: Sequence[Curve], free_scale: bool
) -> GroupSolution:
    """Re-solve the weights exactly for the final grid (the interior point leaves ~1e-9
    where the optimum is 0); kept only if the objective does not grow."""
    w_exact = polish_weights(sol.log_u, curves, free_scale)
    obj_exact = objective(sol.log_u, w_exact, curves)
    if obj_exact <= sol.objective * (1.0 + 1e-9) + 1e-15:
        return GroupSolution(sol.log_u, w_exact, obj_exact, sol.status, sol.iterations, sol.solver)
    return sol


def merge_close_terms(
    sol: GroupSolution, curves: Sequence[Curve], free_scale: bool, tol: float
) -> tuple[GroupSolution, int]:
    """Merge terms whose log-variances differ by less than ``tol``; polish the weights.

    Two nearly equal variances are one blur pass in the renderer; IPOPT splits a
    component when k exceeds what the data supports. The merge is kept only if the
    objective does not grow by more than 1e-6 of the data norm.
    """
    order = np.argsort(sol.log_u)
    log_u, w = sol.log_u[order], sol.weights[:, order]
    merged = 0
    i = 0
    while i < log_u.size - 1:
        if log_u[i + 1] - log_u[i] < tol:
            ww = w[:, i] + w[:, i + 1]
            mass = np.sum(w[:, i : i + 2], axis=0)
            frac = mass[1] / mass.sum() if mass.sum() > 0 else 0.5
            new_lu = (1 - frac) * log_u[i] + frac * log_u[i + 1]
            trial_lu = np.concatenate([log_u[:i], [new_lu], log_u[i + 2 :]])
            trial_w = np.concatenate([w[:, :i], ww[:, None], w[:, i + 2 :]], axis=1)
            trial_w = polish_weights(trial_lu, curves, free_scale)
            trial_obj = objective(trial_lu, trial_w, curves)
            if trial_obj <= sol.objective + 1e-6 * len(curves):
                log_u, w = trial_lu, trial_w
                merged += 1
                continue
        i += 1
    if merged == 0:
        return GroupSolution(log_u, w, sol.objective, sol.status, sol.iterations, sol.solver), 0
    obj = objective(log_u, w, curves)
    return GroupSolution(log_u, w, obj, sol.status, sol.iterations, sol.solver), merged
