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


def _normalised(fit: FitResult) -> NDArray[np.float64]:
    s = fit.weights.sum(axis=0, keepdims=True)
    return fit.weights / np.where(s > 0, s, 1.0)


def diffusion_terms(fits: list[FitResult] | tuple[FitResult, ...], grid: int = 0,
                    single: str | None = None, floor_mm2: float = 0.0) -> DiffusionTerms:
    """The blur schedule for a set of region fits.

    ``grid`` = 0 keeps every fit's own variances (equal ones merged). ``grid`` = N
    re-expresses each region and channel on the smallest variance plus N - 1 log-spaced
    ones from ``floor_mm2`` (narrower blurs are sub-texel and cost nothing) to the
    largest, by
    non-negative least squares on the r-weighted profile (the fit's eq. 2c objective),
    then renormalises the weights to sum to 1. ``single`` = 'mean' or a region name
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
    for r, fit in enumerate(fits):
        w = _normalised(fit)
        if grid > 0:
            radius = np.linspace(0.0, 4.0 * math.sqrt(variances.max()), 400)[1:]
            basis = np.stack([sum_of_gaussians([v], [[1, 1, 1]], radius)[:, 0]
                              for v in variances], axis=1)
            target = sum_of_gaussians(fit.variances_mm2, w, radius)
            sw = np.sqrt(radius)[:, None]
            for c in range(3):
                a, _ = nnls(basis * sw, target[:, c] * sw[:, 0])
                weights[r, :, c] = a / max(a.sum(), 1e-30)
            approx = sum_of_gaussians(variances, weights[r], radius)
            error[fit.name] = float(fit_error_eq2c(radius, approx, target).max())
        else:
            for v, row in zip(fit.variances_mm2, w, strict=True):
                k = int(np.argmin(np.abs(variances - v)))
                weights[r, k] += row
            error[fit.name] = 0.0
    if single is not None:
        shared = weights.mean(axis=0) if single == "mean" else \
            weights[[f.name for f in fits].index(single)]
        weights[:] = shared
        notes.append(f"one profile ({single}) for every region")
    return DiffusionTerms(variances, weights, error, notes)


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
    code = source_of(diffusion_terms, _normalised, sum_of_gaussians, fit_error_eq2c)
    key = content_hash(scipy.__version__, code, MERGE_RELATIVE, grid, single,
                       float(floor_mm2), len(fits),
                       *(part for f in fits for part in
                         (f.name, np.asarray(f.variances_mm2, np.float64),
                          np.asarray(f.weights, np.float64))))

    def read(doc: dict[str, Any]) -> DiffusionTerms:
        variances = np.asarray(doc["variances_mm2"], np.float64)
        weights = np.asarray(doc["weights"], np.float64)
        error = {str(k): float(v) for k, v in doc["error"].items()}
        if variances.ndim != 1 or weights.shape != (len(fits), variances.size, 3) \
                or set(error) != {f.name for f in fits} \
                or not np.all(np.isfinite(weights)) or not np.all(variances > 0):
            raise ValueError("kept terms do not fit the fits")
        return DiffusionTerms(variances, weights, error, [str(n) for n in doc["notes"]])

    def make() -> tuple[DiffusionTerms, dict[str, Any]]:
        terms = diffusion_terms(fits, grid, single, floor_mm2)
        return terms, {"variances_mm2": terms.variances_mm2.tolist(),
                       "weights": terms.weights.tolist(), "error": terms.error,
                       "notes": terms.notes}

    return kept("diffusion-terms", "terms", key, read, make)
