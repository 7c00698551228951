"""What every diffusion takes and reports: the irradiance and the terms checked, the
regions present, and the blur statistics for ``render.json``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError


@dataclass
class BlurStats:
    """What the diffusion did: passes run, passes skipped and why."""

    passes: int = 0
    """Passes over a texture: two per recursive 2D blur, one per direct one."""
    skipped: list[str] = field(default_factory=list)
    levels: list[int] = field(default_factory=list)
    """Pyramid level each blurred term ran on (0: full resolution)."""
    full_blurs: float = 0.0
    """Texels blurred, in full-resolution 2D blurs."""
    tile_texels: dict[int, int] = field(default_factory=dict)
    """Per pyramid level used, the texels of its chart-tile atlas (tiles and margins)."""
    surface_terms: list[tuple[float, int]] = field(default_factory=list)
    """The terms summed on the surface (variance mm^2) and their points' block level."""


def _check_irradiance(irradiance: NDArray[Any]) -> NDArray[np.float32]:
    """(H, W, 3) float32 irradiance, every value finite (else InputError naming a texel)."""
    e = np.asarray(irradiance, dtype=np.float32)
    if e.ndim != 3 or e.shape[2] != 3:
        raise InputError(f"irradiance must be (H, W, 3), got {e.shape}")
    # one float64 sum is finite exactly when every value is (a NaN or inf propagates and
    # float32 values cannot overflow it); the texel is only looked for when it is not
    if not np.isfinite(e.sum(dtype=np.float64)):
        y, x, c = np.argwhere(~np.isfinite(e))[0]
        raise InputError(f"irradiance must be finite; texel ({x}, {y}) channel {c} is {e[y, x, c]}")
    return e


def _region_presence(region_weights: NDArray[Any] | None) -> NDArray[np.bool_] | None:
    """Which regions any texel gives a weight other than +0 (None: one region
    everywhere)."""
    if region_weights is None:
        return None
    n = region_weights.shape[-1]
    # half floats by their bits (non-zero bits: a non-zero weight, or -0): numpy's
    # float16 maximum took 0.27 s at texture 4096
    flat = (region_weights.view(np.uint16) if region_weights.dtype == np.float16
            else region_weights).reshape(-1, n)
    # 64 texels a row: numpy's reduction over rows of only R values took 0.88 s at
    # texture 4096 (the maximum is the same whatever the grouping)
    whole = flat.shape[0] - flat.shape[0] % 64
    parts = [flat[whole:]]
    if whole:
        parts.append(flat[:whole].reshape(-1, 64 * n).max(axis=0).reshape(64, n))
    return np.concatenate(parts).max(axis=0, initial=0) > 0


def unit_region_weights(region_weights: NDArray[np.float32]) -> NDArray[np.float32]:
    """(H, W, R) region weights scaled to sum to 1 at each texel (0 where they sum to
    0), as the blurs read them: a texel is all skin, whatever rounding did to a
    blend."""
    total = region_weights.sum(axis=-1, keepdims=True)
    return np.divide(region_weights, total, out=np.zeros_like(region_weights),
                     where=total > 0)


def _check_terms(
    shape: tuple[int, int], variances_mm2: NDArray[Any], term_weights: NDArray[Any],
    region_shape: tuple[int, ...] | None, present: NDArray[np.bool_] | None,
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_], BlurStats]:
    """Checked variances (K,) and term weights (R, K, 3) against a (H, W[, R]) layout
    (``region_shape``: its region weight map's shape, None without one), which terms any
    present region uses, and stats noting the regions no texel uses."""
    h, w = shape
    v = np.asarray(variances_mm2, dtype=np.float64)
    tw = np.asarray(term_weights, dtype=np.float32)
    if tw.ndim == 2:
        tw = tw[None]
    n_regions = tw.shape[0]
    if v.ndim != 1 or tw.shape != (n_regions, v.size, 3):
        raise InputError(f"term weights must be (R, K, 3) with K = {v.size}, got {tw.shape}")
    if region_shape is None:
        if n_regions != 1:
            raise InputError(f"{n_regions} regions' weights but no region weight map")
    elif tuple(region_shape) != (h, w, n_regions):
        raise InputError(f"region weights must be ({h}, {w}, {n_regions}), "
                         f"got {tuple(region_shape)}")
    if np.any(np.diff(v) < 0) or np.any(v <= 0) or not np.all(np.isfinite(v)):
        raise InputError(f"variances must be finite, > 0 and ascending, got {v.tolist()}")
    stats = BlurStats()
    if present is not None:
        for r in np.flatnonzero(~present):
            stats.skipped.append(f"region {r}: no texel uses it")
        used = (tw[present].max(axis=(0, 2)) > 0) if present.any() else np.zeros(v.size, bool)
    else:
        used = tw[0].max(axis=1) > 0
    return v, tw, used, stats
