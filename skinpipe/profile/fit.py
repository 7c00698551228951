"""Fit stage: sum-of-Gaussians diffusion profiles (Park & Oh 2009, eq. 1 and 2).

Model: f_c(r) = sum_j w_jc G(v_j, r), with G the normalised 2D Gaussian, per channel c
weights w_jc >= 0 summing to 1 (eq. 2b). Objective: eq. 2a with the r (area) weighting
of eq. 2c (and optional per-sample standard deviations), plus the profile's radial
energy: the share of light within each ring's outer edge, fitted to the measured one, so
that the energy goes where the measurement puts it, an entry spike included (the values'
r-weighted residual gives the first samples almost no say, and a fit by values alone
spread a skin profile's spike into its tails: shadow edges 7-18% too hard). The light
within a radius is measured whole even where the image cuts the tail off, so the term
holds for a truncated profile too. Both terms are normalised to the data and weighted
equally (``energy_weight``); :mod:`.edge` reports what a shadow edge shows. A genetic algorithm over
the log-variances seeds casadi's IPOPT, which refines log-variances and weights
together.

The problem is split into independent *groups*: a group is a set of curves (one curve
= one channel of one profile) that share one variance grid. ``share="channels"`` makes
one group per profile, ``"none"`` one per channel, ``"profiles"`` one for a whole face.
"""

from __future__ import annotations

import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property, partial
from typing import Any, Literal

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from ..errors import FitError, InputError
from ..interrupts import raise_if_interrupted
from .edge import edge_report
from .models import fit_error_eq2c, ring_areas_mm2, ring_edges_mm, ring_widths_mm
from .types import CHANNELS, FitResult, FloatArray, MeasuredProfile

Share = Literal["channels", "none", "profiles"]
Solver = Literal["ipopt", "slsqp"]
Init = Literal["ga", "naive", "random"]
ACCEPTED_IPOPT_STATUS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
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


@dataclass(frozen=True)
class FitOptions:
    """How to fit. Radii in mm, variances in mm^2.

    k: Gaussians per variance grid (1-8). share: which curves share a grid.
    fixed_variances_mm2: a given grid (e.g. d'Eon's); only weights are solved.
    min_radius_mm / max_radius_mm: samples outside are left out (the paper drops the
    entry point, eq. 2 sums from i = 2). free_scale: fit the total diffuse reflectance
    per channel too (absolute captures, or a profile truncated by the image) instead of
    sum w = 1. use_stddev: weight samples by 1/std^2 as well as by r dr; off by default
    because eq. 2c weights by area alone. energy_weight: the radial energy term's
    weight against the values' (both normalised to the data; 0: the paper's eq. 2a
    alone).
    """

    k: int = 6
    share: Share = "channels"
    fixed_variances_mm2: tuple[float, ...] | None = None
    min_radius_mm: float = 0.0
    max_radius_mm: float | None = None
    seed: int = 0
    generations: int = 20
    population: int = 32
    solver: Solver = "ipopt"
    init: Init = "ga"
    free_scale: bool = False
    use_stddev: bool = False
    energy_weight: float = 10.0
    max_plausible_radius_mm: float = 100.0
    merge_log_variance: float = 0.02

    def __post_init__(self) -> None:
        # A GA of fewer than 4 or no generations seeds IPOPT at random; it ran without a
        # word before, and a user who asks for it has mistyped.
        if not 1 <= self.generations <= 10_000:
            raise InputError(f"generations must be 1-10000, got {self.generations}")
        if not 4 <= self.population <= 100_000:
            raise InputError(f"population must be 4-100000, got {self.population}")
        if not (math.isfinite(self.energy_weight) and self.energy_weight >= 0):
            raise InputError(f"energy_weight must be finite and >= 0, got {self.energy_weight}")
        if not (math.isfinite(self.min_radius_mm) and self.min_radius_mm >= 0):
            raise InputError(f"min_radius_mm must be finite and >= 0, got {self.min_radius_mm}")
        if self.max_radius_mm is not None and not (
                math.isfinite(self.max_radius_mm) and self.max_radius_mm > self.min_radius_mm):
            raise InputError(f"max_radius_mm must be finite and > min_radius_mm "
                             f"({self.min_radius_mm:g}), got {self.max_radius_mm}")


# --------------------------------------------------------------------------- data prep


@dataclass
class _Curve:
    """One channel of one profile, in the group's scaled units (lengths / L)."""

    rho: FloatArray  # radius / L
    q: FloatArray  # value * L^2 (so that q ~ sum w G(u, rho))
    profile: int
    channel: int
    # The sample weights a = a_scale * a_unit (rho drho / sigma^2, normalised so that the
    # curve's sum a q^2 = 1): the channels of a profile share a_unit (unless weighted by
    # their own standard deviations), so their Gram matrices differ by a factor only.
    a_unit: FloatArray
    a_scale: float
    # The energy term: at the rings' outer edges ``rho_e``, the light within, ``t``, with
    # weights b = b_unit * b_scale (the edges' spacing, shared by a profile's curves;
    # normalised so that the curve's sum b t^2 = energy_weight).
    rho_e: FloatArray
    t: FloatArray
    b_unit: FloatArray
    b_scale: float

    @cached_property
    def a(self) -> FloatArray:
        return self.a_unit * self.a_scale

    @cached_property
    def b(self) -> FloatArray:
        return self.b_unit * self.b_scale


MAX_FIT_SAMPLES = 4000
"""Profiles sampled more finely are averaged in runs of consecutive radii to at most this
many samples before fitting (at 1 um spacing over 4 mm the change in the fitted curve is
below the noise; measured: 80,000 samples took 155 s to fit, 4000 of them 6 s, eq. 2c
6.52e-4 against 6.51e-4)."""


def _average_runs(r: FloatArray, p: FloatArray, s: FloatArray | None, group: int
                  ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Means of consecutive runs of ``group`` samples (sorted radii); standard deviations
    of the means."""
    starts = np.arange(0, r.size, group)
    counts = np.diff(np.r_[starts, r.size])

    def mean(x: FloatArray) -> FloatArray:
        return np.add.reduceat(x, starts, axis=0) / (counts[:, None] if x.ndim == 2 else counts)

    s_mean = None if s is None else np.sqrt(mean(s**2) / counts[:, None])
    return mean(r), mean(p), s_mean


def prepare_profile(
    profile: MeasuredProfile, options: FitOptions
) -> tuple[MeasuredProfile, list[str]]:
    """Validate and tidy one profile for fitting; raise :class:`InputError` on bad data.

    Returns the tidied profile and notes on what was changed.

    Drops non-finite samples (with a warning), sorts by radius, averages duplicate
    radii, applies the fit range, and refuses what no fit can honour: too few samples,
    an all-zero profile, a silent channel (unless ``free_scale``), radii in the wrong
    unit, or a profile whose integral is far from 1 when the weights must sum to 1.
    """
    src = profile.source
    notes: list[str] = []
    r = np.asarray(profile.radius_mm, dtype=np.float64).reshape(-1)
    p = np.asarray(profile.values, dtype=np.float64)
    if p.ndim != 2 or p.shape != (r.size, 3):
        raise InputError(f"values must be (n, 3) for n = {r.size} radii, got {p.shape}", src)
    s = None if profile.stddev is None else np.asarray(profile.stddev, dtype=np.float64)
    if s is not None and s.shape != p.shape:
        raise InputError(f"stddev must have the shape of values {p.shape}, got {s.shape}", src)
    finite = np.isfinite(r) & np.all(np.isfinite(p), axis=1)
    if s is not None:
        finite &= np.all(np.isfinite(s), axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        notes.append(
            f"dropped {bad.size} non-finite sample(s), the first sample {int(bad[0]) + 1} "
            f"(radius {float(r[bad[0]]):g} mm)"
        )
        r, p = r[finite], p[finite]
        s = None if s is None else s[finite]
    if r.size and r.min() < 0:
        raise InputError(f"radius_mm must be >= 0, found {r.min():g}", src)
    order = np.argsort(r, kind="stable")
    r, p = r[order], p[order]
    s = None if s is None else s[order]
    uniq, inverse, counts = np.unique(r, return_inverse=True, return_counts=True)
    if uniq.size < r.size:
        pm = np.zeros((uniq.size, 3))
        np.add.at(pm, inverse, p)
        pm /= counts[:, None]
        if s is not None:
            sm = np.zeros((uniq.size, 3))
            np.add.at(sm, inverse, s**2)
            s = np.sqrt(sm / counts[:, None]) / np.sqrt(counts[:, None])
        notes.append(f"averaged {r.size - uniq.size} sample(s) at duplicate radii")
        r, p = uniq, pm
    if r.size > MAX_FIT_SAMPLES:
        group = -(-r.size // MAX_FIT_SAMPLES)
        notes.append(f"{r.size} samples averaged in runs of {group} (the fit's cost grows "
                     f"with the samples; at most {MAX_FIT_SAMPLES} are kept)")
        r, p, s = _average_runs(r, p, s, group)
    keep = r >= options.min_radius_mm
    if options.max_radius_mm is not None:
        keep &= r <= options.max_radius_mm
    r, p = r[keep], p[keep]
    s = None if s is None else s[keep]
    if r.size and r.max() > options.max_plausible_radius_mm:
        raise InputError(
            f"largest radius is {r.max():g} mm, beyond the plausible "
            f"{options.max_plausible_radius_mm:g} mm for skin: are the radii in micrometres "
            "or pixels rather than mm?",
            src,
        )
    k_eff = _k_of(options)
    needed = 2 * k_eff
    if r.size < max(needed, 3):
        raise InputError(
            f"{r.size} usable samples in the fit range, need at least {max(needed, 3)} for "
            f"k = {k_eff} (k variances and k-1 weights per channel)",
            src,
        )
    scale = np.max(np.abs(p))
    if not scale > 0:
        raise InputError("the profile is zero everywhere: nothing to fit", src)
    if s is not None:
        positive = s[s > 0]
        floor = 1e-3 * float(np.median(positive)) if positive.size else 1.0
        s = np.maximum(s, floor)
    integral = 2.0 * np.pi * np.trapezoid(p * r[:, None], r, axis=0)
    for c in range(3):
        peak = np.max(np.abs(p[:, c]))
        if not peak > 1e-12 * scale and not options.free_scale:
            raise InputError(
                f"channel {CHANNELS[c]} has no signal (max |value| = {peak:g}): a profile whose "
                "weights sum to 1 cannot fit it; check the capture or use --free-scale",
                src,
            )
        if not options.free_scale and not 0.2 <= integral[c] <= 5.0:
            raise InputError(
                f"channel {CHANNELS[c]} integrates to {integral[c]:.4g} over the plane "
                "(2 pi int p r dr), not about 1: normalise the profile (skinpipe ingest does), "
                "check that radii are in mm, or fit with --free-scale",
                src,
            )
    return MeasuredProfile(r, p, s, profile.name, profile.source), notes


MAX_TERMS = 8
"""The most Gaussians a fit takes (k)."""


def check_terms(k: int) -> int:
    """``k`` if a fit can take it (1 to :data:`MAX_TERMS`); InputError otherwise."""
    if not 1 <= k <= MAX_TERMS:
        raise InputError(f"k must be between 1 and {MAX_TERMS}, got {k}")
    return k


def _k_of(options: FitOptions) -> int:
    if options.fixed_variances_mm2 is not None:
        return len(options.fixed_variances_mm2)
    return check_terms(options.k)


def _variance_bounds_mm2(profiles: Sequence[MeasuredProfile], energy: bool = True
                         ) -> tuple[float, float]:
    """Search range for variances: from below the sample spacing to beyond the data. With
    the energy term a term narrower than the first ring is still seen (its light within
    that ring's edge: an entry spike), so the range reaches a quarter spacing, else half."""
    gaps = np.concatenate([np.diff(p.radius_mm) for p in profiles])
    positive = np.concatenate([p.radius_mm[p.radius_mm > 0] for p in profiles])
    smallest = min(float(gaps[gaps > 0].min()), float(positive.min()))
    largest = max(float(p.radius_mm.max()) for p in profiles)
    lo = ((0.25 if energy else 0.5) * smallest) ** 2
    hi = (2.0 * largest) ** 2
    return lo, max(hi, 10.0 * lo)


def _make_curves(
    profiles: Sequence[MeasuredProfile], channels: Sequence[tuple[int, int]], length_mm: float,
    use_stddev: bool = False, energy_weight: float = 1.0,
) -> list[_Curve]:
    curves = []
    rhos: dict[int, tuple[FloatArray, ...]] = {}
    for pi, c in channels:
        prof = profiles[pi]
        if pi not in rhos:
            rho = prof.radius_mm / length_mm
            rho_e = ring_edges_mm(prof.radius_mm) / length_mm
            within = np.cumsum(prof.values * ring_areas_mm2(prof.radius_mm)[:, None], axis=0)
            rhos[pi] = (rho, rho * ring_widths_mm(rho), rho_e, ring_widths_mm(rho_e), within)
        rho, unit, rho_e, b_unit, within = rhos[pi]
        q = prof.values[:, c] * length_mm**2
        if use_stddev and prof.stddev is not None:
            inv_var = 1.0 / (prof.stddev[:, c] * length_mm**2) ** 2
            unit = unit * inv_var / np.mean(inv_var)
        norm = float(np.sum(unit * q * q))
        # A silent channel (free_scale only) keeps unit weights; its amplitude goes to 0.
        scale = 1.0 / norm if norm > 0 else 1.0 / max(float(np.sum(unit)), 1e-300)
        t = within[:, c]
        t_norm = float(np.sum(b_unit * t * t))
        b_scale = energy_weight / t_norm if t_norm > 0 else 0.0
        curves.append(_Curve(rho, q, pi, c, unit, scale, rho_e, t, b_unit, b_scale))
    return curves


# ------------------------------------------------------------------------ weight solves


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


def _gram_weights(hess: FloatArray, grad: FloatArray, free_scale: bool) -> FloatArray:
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


def _basis(log_u: FloatArray, rho: FloatArray) -> FloatArray:
    """G(u, rho) for a batch of log-variances (..., k) at radii (n,) -> (..., n, k)."""
    u = np.exp(log_u)[..., None, :]
    return np.exp(-(rho[:, None] ** 2) / (2.0 * u)) / (2.0 * np.pi * u)


def _energy_basis(log_u: FloatArray, rho: FloatArray) -> FloatArray:
    """The light of G(u) within radius rho, 1 - exp(-rho^2 / 2u), for a batch of
    log-variances (..., k) at radii (n,) -> (..., n, k)."""
    u = np.exp(log_u)[..., None, :]
    return -np.expm1(-(rho[:, None] ** 2) / (2.0 * u))


def _fitness(log_u: FloatArray, curves: Sequence[_Curve], free_scale: bool) -> tuple[
    FloatArray, FloatArray
]:
    """Objective of each candidate grid (P, k) with its best weights -> (P,), (P, C, k)."""
    n_pop, k = log_u.shape
    hess = np.empty((n_pop, len(curves), k, k))
    grad = np.empty((n_pop, len(curves), k))
    const = np.empty(len(curves))
    basis: dict[int, tuple[FloatArray, FloatArray]] = {}
    gram: dict[tuple[int, int], tuple[FloatArray, FloatArray]] = {}
    for ci, cv in enumerate(curves):
        # Curves of one profile share their radii and, up to a factor, their sample
        # weights: evaluate the Gaussians and their Gram matrices once.
        if id(cv.rho) not in basis:
            basis[id(cv.rho)] = (_basis(log_u, cv.rho), _energy_basis(log_u, cv.rho_e))
        b, e = basis[id(cv.rho)]
        key = (id(cv.a_unit), id(cv.b_unit))
        if key not in gram:
            gram[key] = (np.swapaxes(b * cv.a_unit[:, None], 1, 2) @ b,
                         np.swapaxes(e * cv.b_unit[:, None], 1, 2) @ e)
        unit, edge = gram[key]
        hess[:, ci] = cv.a_scale * unit + cv.b_scale * edge
        grad[:, ci] = np.swapaxes(b, 1, 2) @ (cv.a * cv.q) + np.swapaxes(e, 1, 2) @ (cv.b * cv.t)
        const[ci] = float(np.sum(cv.a * cv.q * cv.q) + np.sum(cv.b * cv.t * cv.t))
    w = _gram_weights(hess.reshape(-1, k, k), grad.reshape(-1, k), free_scale)
    w = w.reshape(n_pop, len(curves), k)
    objective = (
        np.einsum("pck,pckl,pcl->p", w, hess, w) - 2.0 * np.einsum("pck,pck->p", w, grad)
        + const.sum()
    )
    return np.maximum(objective, 0.0), w


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


# ----------------------------------------------------------------------------- GA seed

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
    curves: Sequence[_Curve],
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
    fit, _ = _fitness(pop, curves, free_scale)
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
        child_fit, _ = _fitness(child, curves, free_scale)
        pop = np.concatenate([pop[:2], child])
        fit = np.concatenate([fit[:2], child_fit])
    best = int(np.argmin(fit))
    return pop[best], float(fit[best])


SWAP_POSITIONS = 16
"""Log-spaced places across the variance bounds a term may move to in :func:`swap_terms`."""


def swap_terms(
    log_u: FloatArray,
    curves: Sequence[_Curve],
    log_bounds: tuple[float, float],
    free_scale: bool,
    keep: int = 3,
) -> FloatArray:
    """Grids one term away from ``log_u``: each of the k terms moved to each of
    SWAP_POSITIONS places across the bounds that lie a factor e or more from every
    term (a new use for it, not a nudge the refinement makes anyway), all scored
    at once with their best weights (:func:`_fitness`); returns ``log_u`` and the
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
    obj, _ = _fitness(cand, curves, free_scale)
    picked, used = [log_u], []
    for i in np.argsort(obj):
        if len(picked) > keep:
            break
        if all(abs(place[i] - q) > 0.5 for q in used):
            picked.append(cand[i])
            used.append(place[i])
    return np.array(picked)


# ------------------------------------------------------------------------ IPOPT refine


def _upper_gram(left: Any, right: Any, symmetric: bool) -> Any:
    """left' right for (n, k) SX matrices; only the upper triangle when the product is
    symmetric (the lower one is never read: IPOPT takes the Hessian's upper triangle)."""
    k = left.shape[1]
    out = ca.SX.zeros(k, k)
    for i in range(k):
        for j in range(i if symmetric else 0, k):
            out[i, j] = ca.dot(left[:, i], right[:, j])
    return out


def _gauss_newton_problem(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> tuple[dict[str, Any], Any]:
    """The NLP (casadi dict) and its Gauss-Newton Lagrangian Hessian (a casadi Function
    of x, p, lam_f, lam_g giving the upper triangle) for one group's data layout.

    ``layout`` lists, per sample set, (samples, curves using it): curves of one sample
    set share their radii and, up to a factor, their sample weights a = s_c a_unit and
    energy weights b = e_c b_unit (:class:`_Curve`). Decision variables are
    [log-variances (k, unless fixed), weights (k per curve)]; parameters are, per sample
    set, [rho, a_unit, rho_e, b_unit, then q, s_c, t, e_c of each curve], then fixed
    log-variances if any.

    The objective is a weighted sum of squares of two residuals, the values' q - G w and
    the energy's t - E w (E = 1 - exp(-rho_e^2 / 2u), :func:`_energy_basis`), so the Lagrangian
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


def _build_ipopt_solver(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> Any:
    """A casadi IPOPT solver for one group's data layout (:func:`_gauss_newton_problem`):
    0.25 s to build, then reused for every profile of that layout."""
    nlp, hess = _gauss_newton_problem(layout, k, fixed, free_scale)
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


def _ipopt_solver(
    layout: tuple[tuple[int, int], ...], k: int, fixed: bool, free_scale: bool
) -> Any:
    """The calling thread's IPOPT solver for this layout (:func:`_build_ipopt_solver`).

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
        cache[key] = _build_ipopt_solver(layout, k, fixed, free_scale)
    return cache[key]


@dataclass
class _GroupSolution:
    log_u: FloatArray
    weights: FloatArray  # (C, k)
    objective: float
    status: str
    iterations: int
    solver: str


def _objective(log_u: FloatArray, weights: FloatArray, curves: Sequence[_Curve]) -> float:
    total = 0.0
    for ci, cv in enumerate(curves):
        resid = cv.q - _basis(log_u, cv.rho) @ weights[ci]
        edge = cv.t - _energy_basis(log_u, cv.rho_e) @ weights[ci]
        total += float(np.sum(cv.a * resid * resid) + np.sum(cv.b * edge * edge))
    return total


def _polish_weights(log_u: FloatArray, curves: Sequence[_Curve], free_scale: bool) -> FloatArray:
    return np.array([simplex_least_squares(
        np.vstack([_basis(log_u, cv.rho), _energy_basis(log_u, cv.rho_e)]),
        np.concatenate([cv.q, cv.t]), np.concatenate([cv.a, cv.b]), free_scale)
        for cv in curves])


def _layout(curves: Sequence[_Curve]) -> tuple[tuple[tuple[int, int], ...], list[FloatArray]]:
    """Group consecutive curves that share radii and unit sample weights; return the
    layout and the parameter chunks (:func:`_ipopt_solver`)."""
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


def _refine_ipopt(
    curves: Sequence[_Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    fixed: bool,
    free_scale: bool,
) -> _GroupSolution:
    k = log_u0.size
    layout, chunks = _layout(curves)
    solver = _ipopt_solver(layout, k, fixed, free_scale)
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
        start_obj = _objective(log_u0, w0, curves)
        return _GroupSolution(log_u0, w0, start_obj, status, iterations, "ipopt")
    log_u = log_u0 if fixed else x[:k]
    w = np.clip(x[k:] if not fixed else x, 0.0, None).reshape(len(curves), k)
    if not free_scale:
        w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    return _GroupSolution(log_u, w, _objective(log_u, w, curves), status, iterations, "ipopt")


def _refine_slsqp(
    curves: Sequence[_Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    free_scale: bool,
) -> _GroupSolution:
    """scipy's SLSQP on the same problem: the paper's SQP (MATLAB fmincon), for comparison."""
    k, n_c = log_u0.size, len(curves)

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return x[:k], x[k:].reshape(n_c, k)

    def fun(x: FloatArray) -> float:
        lu, w = unpack(x)
        return _objective(lu, w, curves)

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
    return _GroupSolution(lu, w, _objective(lu, w, curves), str(res.message), int(res.nit), "slsqp")


def _with_exact_weights(
    sol: _GroupSolution, curves: Sequence[_Curve], free_scale: bool
) -> _GroupSolution:
    """Re-solve the weights exactly for the final grid (the interior point leaves ~1e-9
    where the optimum is 0); kept only if the objective does not grow."""
    w_exact = _polish_weights(sol.log_u, curves, free_scale)
    obj_exact = _objective(sol.log_u, w_exact, curves)
    if obj_exact <= sol.objective * (1.0 + 1e-9) + 1e-15:
        return _GroupSolution(sol.log_u, w_exact, obj_exact, sol.status, sol.iterations, sol.solver)
    return sol


def _merge_close_terms(
    sol: _GroupSolution, curves: Sequence[_Curve], free_scale: bool, tol: float
) -> tuple[_GroupSolution, int]:
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
            trial_w = _polish_weights(trial_lu, curves, free_scale)
            trial_obj = _objective(trial_lu, trial_w, curves)
            if trial_obj <= sol.objective + 1e-6 * len(curves):
                log_u, w = trial_lu, trial_w
                merged += 1
                continue
        i += 1
    if merged == 0:
        return _GroupSolution(log_u, w, sol.objective, sol.status, sol.iterations, sol.solver), 0
    obj = _objective(log_u, w, curves)
    return _GroupSolution(log_u, w, obj, sol.status, sol.iterations, sol.solver), merged


def _refine(
    curves: Sequence[_Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    options: FitOptions,
) -> _GroupSolution:
    if options.solver == "slsqp":
        return _refine_slsqp(curves, log_u0, w0, log_bounds, options.free_scale)
    return _refine_ipopt(curves, log_u0, w0, log_bounds, False, options.free_scale)


HOP_ROUNDS = 1
"""At most this many one-term moves after the refinement (:func:`_hop_refined`). A second
round never won in 180 fits (the six sample regions and the benchmark's three profiles,
20 seeds each; 25 fits won in the first) and cost every fit that won another three
refinements."""
HOP_TRIES = 3
"""Moves refined per round (:func:`swap_terms`' best). All are refined to convergence:
a move's objective after a few IPOPT iterations does not say where it ends (the
benchmark's skin1 dipole, seed 8: the move that wins by 2% is the highest of the three
after 5, 10 and 30 of its 85 iterations)."""
HOP_BELOW = 1e-8
"""No hops from a solution whose objective per curve (eq. 2c squared) is below this
(eq. 2c 1e-4, ten times below the sample captures' noise): nothing a move could win
matters, and IPOPT spends hundreds of iterations on a zero-residual fit (d'Eon's
noise-free profile: 0.8 -> 1.4 s with hops)."""


def _hop_refined(
    sol: _GroupSolution, curves: Sequence[_Curve], log_bounds: tuple[float, float],
    options: FitOptions,
) -> _GroupSolution:
    """Basin hopping by one term from a refined solution: the best grids one term away
    (:func:`swap_terms`), each refined (:func:`_refine`); the best, if it beats the
    solution by 0.1%, becomes the solution, at most HOP_ROUNDS times. The refined
    optimum's other terms are already near where the new basin wants them, so a move
    lands where one from the GA's seed does not (the sample forehead: 14.8e-6 ->
    11.0e-6). Refined by IPOPT, not by variable projection, which crawls along the
    valley of three close variances (200 iterations to 12.9e-6 where IPOPT reached
    11.0e-6 in 21)."""
    for _ in range(HOP_ROUNDS):
        if sol.objective < HOP_BELOW * len(curves):
            break
        moves = swap_terms(sol.log_u, curves, log_bounds, options.free_scale, keep=HOP_TRIES)
        if moves.shape[0] < 2:
            break
        _, wb = _fitness(moves[1:], curves, options.free_scale)
        tries = _refine_side_by_side(curves, moves[1:], wb, log_bounds, options)
        best = min(tries, key=lambda t: t.objective if np.isfinite(t.objective) else np.inf)
        if not best.objective < sol.objective * (1.0 - 1e-3):
            break
        sol = _GroupSolution(best.log_u, best.weights, best.objective, best.status,
                             sol.iterations + sum(t.iterations for t in tries), best.solver)
    return sol


class _SolverThreads:
    """Threads that each refine with solvers of their own (:func:`_ipopt_solver`), for
    :func:`_refine_side_by_side`. A task goes to a given thread, so that each thread's
    solver for a layout is built ahead (:meth:`build_ahead`, 0.25 s, about a whole
    fit's time) and a move goes only to a thread whose solver is ready."""

    def __init__(self, count: int) -> None:
        # one single-thread executor a thread: a task goes to the thread asked for
        self._threads = [ThreadPoolExecutor(1, thread_name_prefix=f"skinpipe-fit-{i}")
                         for i in range(count)]
        self._asked: set[tuple[int, tuple[Any, ...]]] = set()
        self._ready: set[tuple[int, tuple[Any, ...]]] = set()

    def __len__(self) -> int:
        return len(self._threads)

    def submit(self, thread: int, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        return self._threads[thread].submit(fn, *args)

    def build_ahead(self, key: tuple[Any, ...]) -> None:
        """Each thread builds its solver for ``key`` (:func:`_ipopt_solver`'s arguments),
        unless it was asked to already."""
        for thread in range(len(self)):
            if (thread, key) not in self._asked:
                self._asked.add((thread, key))
                built = self.submit(thread, _ipopt_solver, *key)
                built.add_done_callback(partial(self._built, (thread, key)))

    def _built(self, thread_key: tuple[int, tuple[Any, ...]], built: Future[Any]) -> None:
        if built.exception() is None:  # a failed build fails again in the caller's thread
            self._ready.add(thread_key)

    def ready(self, key: tuple[Any, ...]) -> list[int]:
        """The threads whose solver for ``key`` is built."""
        return [t for t in range(len(self)) if (t, key) in self._ready]


_SOLVER_THREADS: list[_SolverThreads | None] = []
_SOLVER_THREADS_LOCK = threading.Lock()


def _forget_solver_threads() -> None:
    """In a forked child: the parent's solver threads do not exist there (a move sent to
    one would wait for ever), and its lock may have been held by one of them."""
    global _SOLVER_THREADS_LOCK
    _SOLVER_THREADS_LOCK = threading.Lock()
    _SOLVER_THREADS.clear()


os.register_at_fork(after_in_child=_forget_solver_threads)


def _solver_threads() -> _SolverThreads | None:
    """The process's threads for all but one of a hop round's moves, on a machine with two
    cores or more (on two cores three solves side by side beat two then one: 0.134-0.151 s
    against 0.147-0.205 s median a fit). Made once, also when fits start on several
    threads at once."""
    with _SOLVER_THREADS_LOCK:
        if not _SOLVER_THREADS:
            _SOLVER_THREADS.append(_SolverThreads(HOP_TRIES - 1)
                                   if (os.cpu_count() or 1) > 1 else None)
        return _SOLVER_THREADS[0]


def _build_solvers_ahead(curves: Sequence[_Curve], k: int, options: FitOptions) -> None:
    """Have the solver threads build their solvers for this group while the GA runs: on
    three cores or more at once, on two once this thread has its own (a process's first
    fit builds only that: three builds at once on two cores cost it 0.1-0.3 s, more than
    side-by-side moves save in one fit)."""
    threads = _solver_threads()
    if threads is None or options.init != "ga" or options.solver != "ipopt":
        return
    key = _solver_key(curves, k, options)
    if key in getattr(_THREAD_SOLVERS, "cache", {}) or (os.cpu_count() or 1) > 2:
        threads.build_ahead(key)


def _solver_key(curves: Sequence[_Curve], k: int, options: FitOptions) -> tuple[Any, ...]:
    """:func:`_ipopt_solver`'s arguments for refining ``curves`` with ``k`` terms."""
    return (_layout(curves)[0], k, False, options.free_scale)


def _refine_side_by_side(
    curves: Sequence[_Curve], starts: FloatArray, weights: FloatArray,
    log_bounds: tuple[float, float], options: FitOptions,
) -> list[_GroupSolution]:
    """:func:`_refine` from each start, IPOPT's also on the solver threads whose solvers
    are ready; the rest on this thread. Each solve is the same as alone (every thread
    has its own solvers)."""
    threads = _solver_threads() if options.solver == "ipopt" else None
    pairs = list(zip(starts, weights, strict=True))
    away = [threads.submit(t, _refine, curves, s, w, log_bounds, options)
            for t, (s, w) in zip(threads.ready(_solver_key(curves, starts.shape[1], options)),
                                 pairs[1:], strict=False)] if threads else []
    here = [_refine(curves, s, w, log_bounds, options)
            for s, w in [pairs[0], *pairs[1 + len(away):]]]
    return [here[0], *(f.result() for f in away), *here[1:]]


def _solve_group(
    curves: Sequence[_Curve],
    k: int,
    log_bounds: tuple[float, float],
    options: FitOptions,
    rng: np.random.Generator,
    fixed_log_u: FloatArray | None,
) -> tuple[_GroupSolution, list[str]]:
    notes: list[str] = []
    if fixed_log_u is not None:
        w0 = _polish_weights(fixed_log_u, curves, options.free_scale)
        sol = _refine_ipopt(curves, fixed_log_u, w0, log_bounds, True, options.free_scale)
        return _with_exact_weights(sol, curves, options.free_scale), notes
    lo, hi = log_bounds
    _build_solvers_ahead(curves, k, options)
    if options.init == "ga":
        log_u0, _ = genetic_seed(
            curves, k, log_bounds, rng, options.generations, options.population,
            options.free_scale,
        )
    elif options.init == "naive":
        log_u0 = np.linspace(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), k)
    else:
        log_u0 = np.sort(rng.uniform(lo, hi, size=k))
    if options.init == "naive":
        w0 = np.full((len(curves), k), 1.0 / k)
    else:
        _, wb = _fitness(log_u0[None, :], curves, options.free_scale)
        w0 = wb[0]
    seed_obj = _objective(log_u0, w0, curves)
    sol = _refine(curves, log_u0, w0, log_bounds, options)
    if sol.solver == "ipopt" and sol.status not in ACCEPTED_IPOPT_STATUS:
        notes.append(f"IPOPT returned {sol.status}; the result was judged by its objective")
    if not np.isfinite(sol.objective) or sol.objective > seed_obj:
        notes.append("the refinement did not improve on its start; the seed was kept")
        sol = _GroupSolution(log_u0, w0, seed_obj, sol.status, sol.iterations, sol.solver)
    if options.init == "ga" and options.solver == "ipopt":
        sol = _hop_refined(sol, curves, log_bounds, options)
    sol = _with_exact_weights(sol, curves, options.free_scale)
    sol, merged = _merge_close_terms(sol, curves, options.free_scale, options.merge_log_variance)
    if merged:
        notes.append(
            f"{merged} term(s) merged with a neighbour of nearly equal variance: the data "
            f"supports fewer than k = {k} distinct Gaussians"
        )
    return sol, notes


# --------------------------------------------------------------------------- public API


def _groups_for(share: Share, n_profiles: int) -> list[list[tuple[int, int]]]:
    if share == "channels":
        return [[(p, c) for c in range(3)] for p in range(n_profiles)]
    if share == "none":
        return [[(p, c)] for p in range(n_profiles) for c in range(3)]
    if share == "profiles":
        return [[(p, c) for p in range(n_profiles) for c in range(3)]]
    raise InputError(f"share must be one of channels, none, profiles; got {share!r}")


def fit_profiles(
    profiles: Sequence[MeasuredProfile], options: FitOptions | None = None
) -> list[FitResult]:
    """Fit several profiles; with ``share="profiles"`` they share one variance grid.

    Returns one :class:`FitResult` per profile, terms sorted by variance.
    Raises :class:`InputError` for data no fit can honour, :class:`FitError` if the
    optimiser produced non-finite numbers.
    """
    options = options or FitOptions()
    if not profiles:
        raise InputError("no profiles to fit")
    k = _k_of(options)
    start = time.perf_counter()
    prepared, prep_notes = [], []
    for prof in profiles:
        tidy, notes = prepare_profile(prof, options)
        for note in notes:
            warnings.warn(f"{prof.source or prof.name}: {note}", UserWarning, stacklevel=2)
        prepared.append(tidy)
        prep_notes.append(notes)
    rng = np.random.default_rng(options.seed)
    lo_v, hi_v = _variance_bounds_mm2(prepared, options.energy_weight > 0)
    length_mm = math.sqrt(math.sqrt(lo_v * hi_v))
    log_bounds = (math.log(lo_v / length_mm**2), math.log(hi_v / length_mm**2))
    fixed_log_u = None
    if options.fixed_variances_mm2 is not None:
        fv = np.sort(np.asarray(options.fixed_variances_mm2, dtype=np.float64))
        if not np.all(np.isfinite(fv)) or np.any(fv <= 0):
            raise InputError(f"fixed variances must be finite and > 0 mm^2, got {fv.tolist()}")
        fixed_log_u = np.log(fv / length_mm**2)

    per_profile: list[dict[str, Any]] = [
        {"terms": {}, "status": [], "iters": 0, "obj": 0.0, "notes": list(prep_notes[i]),
         "solver": "", "reflectance": np.zeros(3)}
        for i in range(len(profiles))
    ]
    for group in _groups_for(options.share, len(prepared)):
        curves = _make_curves(prepared, group, length_mm, options.use_stddev,
                              options.energy_weight)
        sol, notes = _solve_group(curves, k, log_bounds, options, rng, fixed_log_u)
        if not (np.all(np.isfinite(sol.log_u)) and np.all(np.isfinite(sol.weights))):
            raise FitError(f"the optimiser returned non-finite values (status {sol.status})")
        variances = np.exp(sol.log_u) * length_mm**2
        for ci, (pi, c) in enumerate(group):
            rec = per_profile[pi]
            w = sol.weights[ci]
            if options.free_scale:
                total = float(w.sum())
                rec["reflectance"][c] = total
                w = w / total if total > 0 else np.eye(w.size)[0]
            for v, wj in zip(variances, w, strict=True):
                key = float(v)
                rec["terms"].setdefault(key, np.zeros(3))[c] += wj
            rec["status"].append(sol.status)
            rec["iters"] += sol.iterations
            rec["obj"] += sol.objective / len(group)
            rec["solver"] = ("fixed-grid " if fixed_log_u is not None else "") + (
                f"{options.init}+{sol.solver}"
            )
            rec["notes"].extend(n for n in notes if n not in rec["notes"])
    seconds = time.perf_counter() - start
    results = []
    for pi, prof in enumerate(prepared):
        rec = per_profile[pi]
        keys = sorted(rec["terms"])
        variances = np.array(keys)
        weights = np.array([rec["terms"][key] for key in keys])
        weights[weights < 1e-12] = 0.0
        reflectance = rec["reflectance"] if options.free_scale else None
        statuses = sorted(set(rec["status"]))
        result = FitResult(
            name=prof.name,
            variances_mm2=variances,
            weights=weights,
            error=np.zeros(3),
            seconds=seconds,
            status=",".join(statuses),
            solver=rec["solver"],
            iterations=rec["iters"],
            objective=rec["obj"],
            k_requested=k,
            share=options.share if options.fixed_variances_mm2 is None else "fixed",
            n_samples=int(prof.radius_mm.size),
            radius_range_mm=(float(prof.radius_mm.min()), float(prof.radius_mm.max())),
            total_reflectance=reflectance,
            warnings=rec["notes"],
            source=None if prof.source is None else str(prof.source),
        )
        result.error = fit_error_eq2c(prof.radius_mm, prof.values, result.evaluate(prof.radius_mm))
        result.edge = edge_report(prof.radius_mm, prof.values, variances, weights)
        result.warnings.extend(_beyond_the_measurement(result))
        results.append(result)
    return results


WIDE_TERM_WEIGHT = 0.01
"""A term that carries more light than this in a channel is named when it reaches past
the measured range (:func:`_beyond_the_measurement`)."""


def _beyond_the_measurement(fit: FitResult) -> list[str]:
    """Notes naming each term that puts light where nothing was measured: half its
    light or more beyond the largest radius (its 1.18 sigma, the median of a 2D
    Gaussian's radius, past it), with more than WIDE_TERM_WEIGHT of a channel's light."""
    r_max = fit.radius_range_mm[1]
    notes = []
    for i, (v, w) in enumerate(zip(fit.variances_mm2, fit.weights, strict=True)):
        median_radius = math.sqrt(2.0 * math.log(2.0) * v)
        if median_radius > r_max and w.max() > WIDE_TERM_WEIGHT:
            shares = "/".join(f"{x:.2f}" for x in w)
            notes.append(f"term {i + 1} (variance {v:.4g} mm^2, sigma {math.sqrt(v):.3g} mm, "
                         f"weights R/G/B {shares}) puts half its light beyond the measured "
                         f"{r_max:.3g} mm: that light is extrapolated, not measured")
    return notes


def fit_sum_of_gaussians(
    profile: MeasuredProfile | tuple[ArrayLike, ArrayLike],
    options: FitOptions | None = None,
    **overrides: Any,
) -> FitResult:
    """Fit one RGB profile with a sum of Gaussians (Park & Oh 2009, eq. 1-2).

    ``profile`` is a :class:`MeasuredProfile` or a tuple ``(radius_mm, values)`` of
    numpy arrays. Keyword overrides set :class:`FitOptions` fields, e.g. ``k=4``.
    """
    if not isinstance(profile, MeasuredProfile):
        r, v = profile
        profile = MeasuredProfile(np.asarray(r, float), np.asarray(v, float))
    base = options or FitOptions()
    if overrides:
        base = FitOptions(**{**base.__dict__, **overrides})
    if base.share == "profiles":
        base = FitOptions(**{**base.__dict__, "share": "channels"})
    return fit_profiles([profile], base)[0]


def fit_multistart(
    profile: MeasuredProfile, options: FitOptions | None = None, starts: int = 50
) -> FitResult:
    """Best of ``starts`` IPOPT runs from random log-uniform grids (a reference optimum)."""
    base = options or FitOptions()
    best: FitResult | None = None
    total = 0.0
    for s in range(starts):
        res = fit_sum_of_gaussians(profile, base, init="random", seed=base.seed * 1000 + s)
        total += res.seconds
        if best is None or res.objective < best.objective:
            best = res
    assert best is not None
    best.seconds = total
    best.solver = f"multistart{starts}+ipopt"
    return best
