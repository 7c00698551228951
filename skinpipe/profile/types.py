"""The profile vocabulary every stage shares: a measured radial profile and a fitted sum
of Gaussians (numpy only: reading or writing a profile loads no solver).

Radii in mm, variances in mm^2, RGB weights per term (Park & Oh 2009, eq. 1-2)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .models import sum_of_gaussians

FloatArray = NDArray[np.float64]
CHANNELS = ("R", "G", "B")


@dataclass(frozen=True)
class MeasuredProfile:
    """A radial profile: ``radius_mm`` (n,), ``values`` (n, 3) RGB, optional ``stddev``."""

    radius_mm: FloatArray
    values: FloatArray
    stddev: FloatArray | None = None
    name: str = "profile"
    source: Path | None = None


@dataclass
class FitResult:
    """One profile's fit: terms sorted by variance, eq. 2c error per channel."""

    name: str
    variances_mm2: FloatArray
    weights: FloatArray
    error: FloatArray
    seconds: float
    status: str
    solver: str
    iterations: int
    objective: float
    k_requested: int
    share: str
    n_samples: int
    radius_range_mm: tuple[float, float]
    total_reflectance: FloatArray | None = None
    warnings: list[str] = field(default_factory=list)
    source: str | None = None
    edge: dict[str, FloatArray] | None = None
    """Against the measured profile, per channel (:func:`.edge.edge_report`):
    ``edge_error`` (share of the plateau), ``edge_width_mm`` and
    ``edge_width_measured_mm`` (10-90%), ``shadow_light_ratio``."""

    def evaluate(self, radius_mm: ArrayLike) -> FloatArray:
        """The fitted profile f(r) (n, 3), times the total reflectance if one was fitted."""
        f = sum_of_gaussians(self.variances_mm2, self.weights, radius_mm)
        return f if self.total_reflectance is None else f * self.total_reflectance

    def to_json(self) -> dict[str, Any]:
        """The FIT.json document (see docs/fit.md): the fit's content only. How long it
        took is a fact of the run, kept in run records (the CLI's output, report.json, a
        batch task's done.json), so that the same inputs give the same file."""
        # float32-exact numbers: USD stores them as float/color3f without any change,
        # so FIT.json -> USD -> read back is an identity.
        doc: dict[str, Any] = {
            "name": self.name,
            "terms": [
                {"variance_mm2": _f32(v), "weights": [_f32(x) for x in w]}
                for v, w in zip(self.variances_mm2, self.weights, strict=True)
            ],
            "error": [_f32(e) for e in self.error],
            "error_measure": "Park & Oh 2009 eq. 2c (relative, r-weighted RMS), per channel",
            "status": self.status,
            "solver": self.solver,
            "iterations": int(self.iterations),
            "objective": float(self.objective),
            "k_requested": int(self.k_requested),
            "share": self.share,
            "n_samples": int(self.n_samples),
            "radius_range_mm": [float(x) for x in self.radius_range_mm],
            "units": {"radius": "mm", "variance": "mm^2"},
            "channels": list(CHANNELS),
            "warnings": list(self.warnings),
        }
        if self.edge is not None:
            doc["edge"] = {key: [_f32(x) for x in value] for key, value in self.edge.items()}
            doc["edge_measure"] = ("a hard shadow edge: the largest difference of the edge-"
                                   "spread function as a share of the plateau, the 10-90% "
                                   "width, the light in the shadow (docs/fit.md)")
        if self.total_reflectance is not None:
            doc["total_reflectance"] = [float(x) for x in self.total_reflectance]
        if self.source is not None:
            doc["source"] = self.source
        return doc


def _f32(x: float) -> float:
    return float(np.float32(x))


def fit_result_from_json(doc: dict[str, Any], name: str | None = None) -> FitResult:
    """Read a FIT.json document back (the inverse of :meth:`FitResult.to_json`)."""
    try:
        terms = doc["terms"]
        variances = np.array([float(t["variance_mm2"]) for t in terms])
        weights = np.array([[float(x) for x in t["weights"]] for t in terms]).reshape(-1, 3)
        error = np.array([float(x) for x in doc.get("error", [math.nan] * 3)])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"not a fit document: {exc!r}") from exc
    tr = doc.get("total_reflectance")
    edge = doc.get("edge")
    try:
        edge = None if edge is None else {str(k): np.array([float(x) for x in v]).reshape(3)
                                          for k, v in dict(edge).items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"not a fit document: edge: {exc!r}") from exc
    return FitResult(
        name=name or str(doc.get("name", "profile")),
        variances_mm2=variances,
        weights=weights,
        error=error,
        seconds=float(doc.get("seconds", 0.0)),
        status=str(doc.get("status", "unknown")),
        solver=str(doc.get("solver", "unknown")),
        iterations=int(doc.get("iterations", 0)),
        objective=float(doc.get("objective", math.nan)),
        k_requested=int(doc.get("k_requested", len(terms))),
        share=str(doc.get("share", "channels")),
        n_samples=int(doc.get("n_samples", 0)),
        radius_range_mm=tuple(doc.get("radius_range_mm", (0.0, 0.0))),  # type: ignore[arg-type]
        total_reflectance=None if tr is None else np.array(tr, dtype=np.float64),
        warnings=list(doc.get("warnings", [])),
        source=doc.get("source"),
        edge=edge,
    )
