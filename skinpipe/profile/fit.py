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
from functools import partial
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from ..errors import FitError, InputError
from .edge import edge_report
from .genetic_seed import genetic_seed, swap_terms
from .ipopt_refine import (
    GroupSolution,
    has_ipopt_solver,
    ipopt_solver,
    merge_close_terms,
    parameter_layout,
    refine_ipopt,
    refine_slsqp,
    with_exact_weights,
)
from .models import fit_error_eq2c, ring_areas_mm2, ring_edges_mm, ring_widths_mm
from .objective import Curve, grid_fitness, objective, polish_weights
from .types import CHANNELS, FitResult, FloatArray, MeasuredProfile

Share = Literal["channels", "none", "profiles"]
Solver = Literal["ipopt", "slsqp"]
Init = Literal["ga", "naive", "random"]
ACCEPTED_IPOPT_STATUS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
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
) -> list[Curve]:
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
        curves.append(Curve(rho, q, pi, c, unit, scale, rho_e, t, b_unit, b_scale))
    return curves


def _refine(
    curves: Sequence[Curve],
    log_u0: FloatArray,
    w0: FloatArray,
    log_bounds: tuple[float, float],
    options: FitOptions,
) -> GroupSolution:
    if options.solver == "slsqp":
        return refine_slsqp(curves, log_u0, w0, log_bounds, options.free_scale)
    return refine_ipopt(curves, log_u0, w0, log_bounds, False, options.free_scale)


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
    sol: GroupSolution, curves: Sequence[Curve], log_bounds: tuple[float, float],
    options: FitOptions,
) -> GroupSolution:
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
        _, wb = grid_fitness(moves[1:], curves, options.free_scale)
        tries = _refine_side_by_side(curves, moves[1:], wb, log_bounds, options)
        best = min(tries, key=lambda t: t.objective if np.isfinite(t.objective) else np.inf)
        if not best.objective < sol.objective * (1.0 - 1e-3):
            break
        sol = GroupSolution(best.log_u, best.weights, best.objective, best.status,
                             sol.iterations + sum(t.iterations for t in tries), best.solver)
    return sol


class _SolverThreads:
    """Threads that each refine with solvers of their own (:func:`ipopt_solver`), for
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
        """Each thread builds its solver for ``key`` (:func:`ipopt_solver`'s arguments),
        unless it was asked to already."""
        for thread in range(len(self)):
            if (thread, key) not in self._asked:
                self._asked.add((thread, key))
                built = self.submit(thread, ipopt_solver, *key)
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


def _build_solvers_ahead(curves: Sequence[Curve], k: int, options: FitOptions) -> None:
    """Have the solver threads build their solvers for this group while the GA runs: on
    three cores or more at once, on two once this thread has its own (a process's first
    fit builds only that: three builds at once on two cores cost it 0.1-0.3 s, more than
    side-by-side moves save in one fit)."""
    threads = _solver_threads()
    if threads is None or options.init != "ga" or options.solver != "ipopt":
        return
    key = _solver_key(curves, k, options)
    if has_ipopt_solver(key) or (os.cpu_count() or 1) > 2:
        threads.build_ahead(key)


def _solver_key(curves: Sequence[Curve], k: int, options: FitOptions) -> tuple[Any, ...]:
    """:func:`ipopt_solver`'s arguments for refining ``curves`` with ``k`` terms."""
    return (parameter_layout(curves)[0], k, False, options.free_scale)


def _refine_side_by_side(
    curves: Sequence[Curve], starts: FloatArray, weights: FloatArray,
    log_bounds: tuple[float, float], options: FitOptions,
) -> list[GroupSolution]:
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
    curves: Sequence[Curve],
    k: int,
    log_bounds: tuple[float, float],
    options: FitOptions,
    rng: np.random.Generator,
    fixed_log_u: FloatArray | None,
) -> tuple[GroupSolution, list[str]]:
    notes: list[str] = []
    if fixed_log_u is not None:
        w0 = polish_weights(fixed_log_u, curves, options.free_scale)
        sol = refine_ipopt(curves, fixed_log_u, w0, log_bounds, True, options.free_scale)
        return with_exact_weights(sol, curves, options.free_scale), notes
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
        _, wb = grid_fitness(log_u0[None, :], curves, options.free_scale)
        w0 = wb[0]
    seed_obj = objective(log_u0, w0, curves)
    sol = _refine(curves, log_u0, w0, log_bounds, options)
    if sol.solver == "ipopt" and sol.status not in ACCEPTED_IPOPT_STATUS:
        notes.append(f"IPOPT returned {sol.status}; the result was judged by its objective")
    if not np.isfinite(sol.objective) or sol.objective > seed_obj:
        notes.append("the refinement did not improve on its start; the seed was kept")
        sol = GroupSolution(log_u0, w0, seed_obj, sol.status, sol.iterations, sol.solver)
    if options.init == "ga" and options.solver == "ipopt":
        sol = _hop_refined(sol, curves, log_bounds, options)
    sol = with_exact_weights(sol, curves, options.free_scale)
    sol, merged = merge_close_terms(sol, curves, options.free_scale, options.merge_log_variance)
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
