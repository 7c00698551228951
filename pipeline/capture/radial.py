"""The radial profile around the entry point (ingest, step 2): the entry point to
sub-pixel accuracy, ring statistics in mm, hair strands masked.

Park & Oh 2009, section 2 read one cross-section through the entry point; rings with a
median over angle are robust to hair and follicle shadows (the cross-section is kept as
a mode for comparison). See docs/ingest.md.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates, median_filter

from ..errors import InputError
from ..profile.types import MeasuredProfile

FloatImage = NDArray[np.float32]
ProfileMode = Literal["rings", "cross_section"]


def _weighted_centroid(hdr: FloatImage, window_px: float) -> tuple[float, float]:
    """Iteratively re-weighted centroid under a Gaussian window, background subtracted.

    Starts at the brightest pixel after a 3x3 median (which ignores hot pixels). For a
    radially symmetric spot the true centre is the fixed point, whatever the pixel grid.
    """
    lum = hdr.sum(axis=2).astype(np.float64)
    smooth = median_filter(lum, size=3, mode="nearest")
    y0, x0 = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    half = math.ceil(4 * window_px)
    ys = slice(max(0, y0 - half), min(lum.shape[0], y0 + half + 1))
    xs = slice(max(0, x0 - half), min(lum.shape[1], x0 + half + 1))
    patch = lum[ys, xs]
    background = float(np.median(lum))
    mass = np.maximum(patch - background, 0.0)
    if not mass.sum() > 0:
        raise InputError("no lit spot found: the merged image is flat")
    yy, xx = np.mgrid[ys, xs].astype(np.float64)
    cx, cy = float(x0), float(y0)
    for _ in range(50):
        w = mass * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * window_px**2))
        nx, ny = float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())
        done = abs(nx - cx) + abs(ny - cy) < 1e-4
        cx, cy = nx, ny
        if done:
            break
    return cx, cy


def find_entry_point(hdr: FloatImage, radius_px: int | None = None) -> tuple[float, float]:
    """Sub-pixel entry point (x, y) in pixel coordinates (pixel centres at integers).

    The centre of point symmetry of the log-intensity: the c minimising
    sum |f(c + d) - f(c - d)| over offsets d within ``radius_px``, f interpolated
    (cubic). ``radius_px`` defaults to where the spot falls to 30% of its peak (a
    flat-topped dipole spot needs a wide window). The sum leaves out the half most
    asymmetric pairs: a dark hair strand breaks the symmetry on a few pixels whatever c
    is, and must not pull the estimate as it pulls a centroid. Starts from a tight
    centroid around the brightest pixel.
    """
    from scipy.ndimage import spline_filter  # lazy: 0.25 s to import
    from scipy.optimize import minimize  # lazy: 0.50 s to import

    start = _weighted_centroid(hdr, window_px=1.5)
    lum = hdr.sum(axis=2).astype(np.float64)
    peak = float(lum.max())
    f = np.log(np.maximum(lum, 1e-6 * peak))
    if radius_px is None:
        yy0, xx0 = np.indices(lum.shape)
        ring = np.hypot(xx0 - start[0], yy0 - start[1]).astype(np.int64).ravel()
        mean = np.bincount(ring, lum.ravel()) / np.maximum(np.bincount(ring), 1)
        below = np.flatnonzero(mean < 0.3 * mean[0])
        radius_px = int(np.clip(below[0] if below.size else 12, 8, 60))
    coeffs = spline_filter(f, order=3)
    yy, xx = np.mgrid[-radius_px : radius_px + 1, -radius_px : radius_px + 1]
    half = (yy > 0) | ((yy == 0) & (xx > 0))
    inside = half & (xx**2 + yy**2 <= radius_px**2)
    dx, dy = xx[inside].astype(np.float64), yy[inside].astype(np.float64)
    keep = int(0.5 * dx.size)

    def asymmetry(c: NDArray[np.float64]) -> float:
        a = map_coordinates(coeffs, [c[1] + dy, c[0] + dx], order=3, prefilter=False,
                            mode="nearest")
        b = map_coordinates(coeffs, [c[1] - dy, c[0] - dx], order=3, prefilter=False,
                            mode="nearest")
        diff = np.abs(a - b)
        # trimmed: the most asymmetric half are hair or follicles, whatever c is
        return float(np.partition(diff, keep)[:keep].sum())

    res = minimize(asymmetry, np.array(start), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-9, "initial_simplex":
                            np.array(start) + np.array([[0, 0], [0.5, 0], [0, 0.5]])})
    cx, cy = float(res.x[0]), float(res.x[1])
    if np.hypot(cx - start[0], cy - start[1]) > max(3.0, 0.25 * radius_px):
        return start  # the symmetry search wandered off: keep the centroid (+-1 px)
    return cx, cy


def radial_profile(
    hdr: FloatImage,
    centre_px: tuple[float, float],
    mm_per_pixel: float,
    ring_width_px: float = 1.0,
    max_radius_mm: float | None = None,
    mode: ProfileMode = "rings",
    variance: NDArray[np.float64] | None = None,
    exclude: NDArray[np.bool_] | None = None,
) -> MeasuredProfile:
    """The radial profile around ``centre_px`` with per-sample standard errors.

    ``rings``: the median over each ring of width ``ring_width_px`` (robust to hair and
    follicle shadows), at the ring's median pixel distance; standard error from the
    median absolute deviation (1.2533 * 1.4826 MAD / sqrt(n)), and no smaller than what
    the sensor's noise alone gives (``variance``, per pixel: sqrt(pi/2 sum var) / n, the
    median's efficiency); without ``variance``, no smaller than 1% of the value. Pixels
    in ``exclude`` (hair, :func:`hair_mask`) are left out of the rings.
    ``cross_section``: Park & Oh's single horizontal line through the entry point,
    bilinearly sampled, left and right sides averaged; their half-difference as error.
    """
    h, w, _ = hdr.shape
    cx, cy = centre_px
    limit_px = min(cx, cy, w - 1 - cx, h - 1 - cy)
    if max_radius_mm is not None:
        limit_px = min(limit_px, max_radius_mm / mm_per_pixel)
    if limit_px < 4 * ring_width_px:
        raise InputError(f"the entry point ({cx:.1f}, {cy:.1f}) is too close to the image border")
    if mode == "cross_section":
        radii = np.arange(0.0, limit_px, ring_width_px)
        left = np.stack([map_coordinates(hdr[..., c], [np.full_like(radii, cy), cx - radii],
                                         order=1) for c in range(3)], axis=1)
        right = np.stack([map_coordinates(hdr[..., c], [np.full_like(radii, cy), cx + radii],
                                          order=1) for c in range(3)], axis=1)
        values = 0.5 * (left + right)
        stderr = 0.5 * np.abs(left - right)
        return MeasuredProfile(radii * mm_per_pixel, values, _floor_std(stderr, values))
    yy, xx = np.mgrid[0:h, 0:w]
    dist = np.hypot(xx - cx, yy - cy).ravel()
    ring = np.floor(dist / ring_width_px + 0.5).astype(np.int64)
    n_rings = int(limit_px / ring_width_px)
    keep = ring < n_rings
    if exclude is not None:
        keep &= ~exclude.ravel()
    ring, dist = ring[keep], dist[keep]
    pix = hdr.reshape(-1, 3)[keep].astype(np.float64)
    var = None if variance is None else variance.reshape(-1, 3)[keep]
    order = np.argsort(ring, kind="stable")
    ring, dist, pix = ring[order], dist[order], pix[order]
    var = None if var is None else var[order]
    bounds = np.searchsorted(ring, np.arange(n_rings + 1))
    radii = np.empty(n_rings)
    values = np.empty((n_rings, 3))
    stderr = np.empty((n_rings, 3))
    for i in range(n_rings):
        a, b = bounds[i], bounds[i + 1]
        if b <= a:
            radii[i] = i * ring_width_px
            values[i] = np.nan
            stderr[i] = np.nan
            continue
        seg = pix[a:b]
        med = np.median(seg, axis=0)
        mad = np.median(np.abs(seg - med), axis=0)
        radii[i] = float(np.median(dist[a:b]))
        values[i] = med
        stderr[i] = 1.2533 * 1.4826 * mad / math.sqrt(b - a)
        if var is not None:
            stderr[i] = np.maximum(stderr[i], np.sqrt(0.5 * math.pi * var[a:b].sum(axis=0))
                                   / (b - a))
    ok = np.isfinite(values).all(axis=1)
    if var is not None:
        ok &= np.isfinite(stderr).all(axis=1)
        return MeasuredProfile(radii[ok] * mm_per_pixel, values[ok], stderr[ok])
    return MeasuredProfile(radii[ok] * mm_per_pixel, values[ok],
                           _floor_std(stderr[ok], values[ok]))


HAIR_RATIO = 0.6
"""A pixel darker than this share of the radial model at its radius (3 x 3 median of
the ratio: a strand is 1.5-3 px wide) is hair; the paper's strands pass 10-50% of the
light."""
HAIR_CORE_PX = 3.0
HAIR_CORE_LIMIT = 0.5
"""A capture whose entry point is hair, or whose core (within HAIR_CORE_PX of it) is
more than this share hair, is refused: the paper re-shot such spots. A strand passing
2-4 px beside the entry point covers 15-40% of the core and is masked."""


def hair_mask(hdr: FloatImage, centre_px: tuple[float, float], profile_px: MeasuredProfile,
              variance: NDArray[np.float64] | None = None) -> NDArray[np.bool_]:
    """Hair strands as dark outliers against the radial model: pixels whose luminance,
    3 x 3 median filtered, is below HAIR_RATIO of the profile at their radius, where the
    model stands 10 noise sigmas above zero (or, without a noise model, above 1% of its
    peak), grown by one pixel for the strands' soft edges. ``profile_px``: radii in px."""
    h, w, _ = hdr.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - centre_px[0], yy - centre_px[1])
    lum = hdr.astype(np.float64).sum(axis=2)
    model = np.interp(r, profile_px.radius_mm, profile_px.values.sum(axis=1), right=np.nan)
    ratio = median_filter(lum / np.where(model > 0, model, np.nan), size=3, mode="nearest")
    if variance is not None:
        trusted = model > 10.0 * np.sqrt(np.where(np.isfinite(variance), variance, np.inf)
                                         .sum(axis=2))
    else:
        trusted = model > 0.01 * np.nanmax(model)
    dark = trusted & (ratio < HAIR_RATIO)
    grown = dark.copy()
    grown[1:] |= dark[:-1]
    grown[:-1] |= dark[1:]
    grown[:, 1:] |= dark[:, :-1]
    grown[:, :-1] |= dark[:, 1:]
    return grown


def hair_over_core(hair: NDArray[np.bool_], centre_px: tuple[float, float]
                   ) -> tuple[float, bool]:
    """The share of the core (within HAIR_CORE_PX of the entry point) that ``hair``
    covers, and whether it covers the entry point's own pixel."""
    yy, xx = np.mgrid[0:hair.shape[0], 0:hair.shape[1]]
    core = np.hypot(xx - centre_px[0], yy - centre_px[1]) <= HAIR_CORE_PX
    return float(hair[core].mean()), bool(hair[round(centre_px[1]), round(centre_px[0])])


def _floor_std(stderr: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    # A ring of one or two pixels has no spread to measure: assume 1% of the value.
    floor = 0.01 * np.abs(values) + 1e-12 * np.abs(values).max()
    return np.maximum(stderr, floor)
