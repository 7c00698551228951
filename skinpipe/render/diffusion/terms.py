"""The blur terms of a render: every skin profile's sum of Gaussians on one variance
grid (equal variances merged, zero terms dropped, optionally refitted onto a smaller
grid), with each region's weights per term."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ...profile.models import fit_error_eq2c, sum_of_gaussians
from ...profile.types import FitResult
from ..cache import kept, source_of
from ..scene import content_hash

MERGE_RELATIVE = 1e-3
"""Variances closer than this (relative) share one blur."""


# ------------------------------------------------------------------------ profiles


@dataclass(frozen=True)
class DiffusionTerms:
    """Variances (K,) mm^2 shared by all regions and each region's weights (R, K, 3),
    with the eq. 2c error of re-expressing each region's fit on them."""

    variances_mm2: NDArray[np.float64]
    weights: NDArray[np.float64]
    error: dict[str, float]
    notes: list[str]
    edge_error: dict[str, float]
    """Per region, the largest difference of the light within a radius (share of the
    total) between the fit and its terms on the grid."""


def _light_within(variances_mm2: Any, weights: Any, radius_mm: NDArray[np.float64]
                  ) -> NDArray[np.float64]:
    """The light of sum_i w_i G(v_i) within each radius (n, channels)."""
    v = np.asarray(variances_mm2, dtype=np.float64)[None, :]
    return -np.expm1(-radius_mm[:, None] ** 2 / (2 * v)) @ np.asarray(weights, np.float64)


def _normalised(fit: FitResult) -> NDArray[np.float64]:
    s = fit.weights.sum(axis=0, keepdims=True)
    return fit.weights / np.where(s > 0, s, 1.0)


def diffusion_terms(fits: list[FitResult] | tuple[FitResult, ...], grid: int = 0,
                    single: str | None = None, floor_mm2: float = 0.0) -> DiffusionTerms:
    """The blur schedule for a set of region fits.

    ``grid`` = 0 keeps every fit's own variances (equal ones merged), and so does a
    ``grid`` of at least that many. ``grid`` = N
    re-expresses each region and channel on the smallest variance plus N - 1 log-spaced
    ones from ``floor_mm2`` (narrower blurs are sub-texel and cost nothing) to the
    largest, by non-negative least squares on the profile's light within each radius
    (log-spaced radii from a tenth of the narrowest term's sigma to four of the widest:
    every scale has its say, an entry spike's too) and, weighted a tenth as much, its
    r-weighted values (the fit's two residuals, :mod:`skinpipe.profile.fit`), then
    renormalises the weights to sum to 1. The error kept per region is eq. 2c of the
    values (linear radii) and, in ``edge_error``, the largest difference of the light
    within a radius (what a shadow edge shows). ``single`` = 'mean' or a region name
    gives every region the same profile (the paper's comparison with one profile).
    """
    from scipy.optimize import nnls  # lazy: 0.50 s to import

    fits = list(fits)
    notes: list[str] = []
    if single is not None:
        names = [f.name for f in fits]
        if single != "mean" and single not in names:
            raise InputError(f"single profile {single!r}: not one of {names} or 'mean'")
    all_v = np.concatenate([f.variances_mm2 for f in fits])
    own = np.unique(all_v)
    if grid > 0 and np.count_nonzero(
            np.concatenate([[True], np.diff(own) > MERGE_RELATIVE * own[1:]])) <= grid:
        grid = 0  # the fits' own variances are no more passes than the grid: exact
    if grid > 0:
        lo, hi = float(all_v.min()), float(all_v.max())
        start = min(max(lo, floor_mm2), hi)
        variances = np.unique(np.concatenate([[lo], np.geomspace(start, hi, grid - 1)])) \
            if grid > 1 and hi > lo * 1.0001 else np.array([lo])
    else:
        variances = np.sort(all_v)
        keep = np.concatenate([[True], np.diff(variances) > MERGE_RELATIVE * variances[1:]])
        merged = int((~keep).sum())
        if merged:
            notes.append(f"{merged} equal variance(s) merged into one blur")
        variances = variances[keep]
    weights = np.zeros((len(fits), variances.size, 3))
    error: dict[str, float] = {}
    edge_error: dict[str, float] = {}
    for r, fit in enumerate(fits):
        w = _normalised(fit)
        if grid > 0:
            radius = np.linspace(0.0, 4.0 * math.sqrt(variances.max()), 400)[1:]
            basis = np.stack([sum_of_gaussians([v], [[1, 1, 1]], radius)[:, 0]
                              for v in variances], axis=1)
            target = sum_of_gaussians(fit.variances_mm2, w, radius)
            sw = np.sqrt(radius * radius[0])[:, None]
            log_r = np.geomspace(0.1 * math.sqrt(min(all_v.min(), variances.min())),
                                 4.0 * math.sqrt(max(all_v.max(), variances.max())), 400)
            within = _light_within(variances, np.eye(variances.size), log_r)
            target_within = _light_within(fit.variances_mm2, w, log_r)
            for c in range(3):
                scale = 0.1 / max(float(np.linalg.norm(target[:, c] * sw[:, 0])), 1e-300)
                a, _ = nnls(np.vstack([within, scale * basis * sw]),
                            np.concatenate([target_within[:, c], scale * target[:, c] * sw[:, 0]]))
                weights[r, :, c] = a / max(a.sum(), 1e-30)
            approx = sum_of_gaussians(variances, weights[r], radius)
            error[fit.name] = float(fit_error_eq2c(radius, approx, target).max())
            edge_error[fit.name] = float(np.abs(
                _light_within(variances, weights[r], log_r) - target_within).max())
        else:
            for v, row in zip(fit.variances_mm2, w, strict=True):
                k = int(np.argmin(np.abs(variances - v)))
                weights[r, k] += row
            error[fit.name] = edge_error[fit.name] = 0.0
    if single is not None:
        shared = weights.mean(axis=0) if single == "mean" else \
            weights[[f.name for f in fits].index(single)]
        weights[:] = shared
        notes.append(f"one profile ({single}) for every region")
    return DiffusionTerms(variances, weights, error, notes, edge_error)


def kept_diffusion_terms(fits: list[FitResult] | tuple[FitResult, ...], grid: int = 0,
                         single: str | None = None, floor_mm2: float = 0.0
                         ) -> DiffusionTerms:
    """:func:`diffusion_terms`, kept in skinpipe's cache folder (:mod:`.kept`) by scipy's
    version, the source of the functions that make them and every input (the fits'
    names, variances and weights, ``grid``, ``single``, ``floor_mm2``): the same terms
    bit for bit. Importing scipy.optimize for its NNLS took 0.44 s of a render's main
    thread before its rays (0.5 s of CPU, the other core mostly idle); a render of the
    same fits at the same texel size reads them back instead."""
    import scipy

    fits = list(fits)
    # the code that makes them is in the key too, with scipy's version: terms made by an
    # edited function are not read back
    code = source_of(diffusion_terms, _normalised, _light_within, sum_of_gaussians,
                     fit_error_eq2c)
    key = content_hash(scipy.__version__, code, MERGE_RELATIVE, grid, single,
                       float(floor_mm2), len(fits),
                       *(part for f in fits for part in
                         (f.name, np.asarray(f.variances_mm2, np.float64),
                          np.asarray(f.weights, np.float64))))

    def read(doc: dict[str, Any]) -> DiffusionTerms:
        variances = np.asarray(doc["variances_mm2"], np.float64)
        weights = np.asarray(doc["weights"], np.float64)
        error = {str(k): float(v) for k, v in doc["error"].items()}
        edge = {str(k): float(v) for k, v in doc["edge_error"].items()}
        if variances.ndim != 1 or weights.shape != (len(fits), variances.size, 3) \
                or set(error) != {f.name for f in fits} or set(edge) != set(error) \
                or not np.all(np.isfinite(weights)) or not np.all(variances > 0):
            raise ValueError("kept terms do not fit the fits")
        return DiffusionTerms(variances, weights, error, [str(n) for n in doc["notes"]],
                              edge)

    def make() -> tuple[DiffusionTerms, dict[str, Any]]:
        terms = diffusion_terms(fits, grid, single, floor_mm2)
        return terms, {"variances_mm2": terms.variances_mm2.tolist(),
                       "weights": terms.weights.tolist(), "error": terms.error,
                       "notes": terms.notes, "edge_error": terms.edge_error}

    return kept("diffusion-terms", "terms", key, read, make)
