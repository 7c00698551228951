"""The radial profile around the entry point (ingest, step 2): the entry point to
sub-pixel accuracy, ring statistics in mm, hair strands masked.

Park & Oh 2009, section 2 read one cross-section through the entry point; rings with a
median over angle are robust to hair and follicle shadows (the cross-section is kept as
a mode for comparison). See docs/ingest.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import special
from scipy.ndimage import label, map_coordinates, median_filter

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


ENTRY_GRID_PX = 8
ENTRY_REFINE_GRID_PX = 2
ENTRY_GRID_RADIUS_PX = 12
"""The entry point's search first compares whole-pixel positions within ENTRY_GRID_PX
of its start (ENTRY_REFINE_GRID_PX when hair is already masked: the start is then the
last estimate), by the symmetry of the pixels within ENTRY_GRID_RADIUS_PX (0.15 ms a
position), then refines the best over the whole spot: with a strand across a
flat-topped (dipole) spot the search from the brightest pixel stopped 6 px from the
entry point, whose asymmetry is 50x lower."""


def find_entry_point(hdr: FloatImage, radius_px: int | None = None,
                     exclude: NDArray[np.bool_] | None = None,
                     start: tuple[float, float] | None = None) -> tuple[float, float]:
    """Sub-pixel entry point (x, y) in pixel coordinates (pixel centres at integers).

    The centre of point symmetry of the log-intensity: the c minimising the mean of
    |f(c + d) - f(c - d)| over offsets d within ``radius_px``, f interpolated (cubic).
    ``radius_px`` defaults to where the spot falls to 30% of its peak (a flat-topped
    dipole spot needs a wide window). The mean leaves out the half most asymmetric
    pairs: a dark hair strand breaks the symmetry on a few pixels whatever c is, and
    must not pull the estimate as it pulls a centroid; pairs with a pixel in
    ``exclude`` (hair found so far) are left out altogether (a strand across the entry
    point is symmetric about a line through it, and the trimmed search can settle
    beside it). Starts from ``start``, else a tight centroid around the brightest
    pixel, with a search over whole pixels around it (:data:`ENTRY_GRID_PX`).
    """
    from scipy.ndimage import spline_filter  # lazy: 0.25 s to import
    from scipy.optimize import minimize  # lazy: 0.50 s to import

    if start is None:
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
    h, w = lum.shape

    def excluded(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
        assert exclude is not None
        return exclude[np.clip(np.rint(y).astype(int), 0, h - 1),
                       np.clip(np.rint(x).astype(int), 0, w - 1)]

    def offsets(radius: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
        half = (yy > 0) | ((yy == 0) & (xx > 0))
        inside = half & (xx**2 + yy**2 <= radius**2)
        return xx[inside].astype(np.float64), yy[inside].astype(np.float64)

    def asymmetry(c: NDArray[np.float64]) -> float:
        a = map_coordinates(coeffs, [c[1] + dy, c[0] + dx], order=3, prefilter=False,
                            mode="nearest")
        b = map_coordinates(coeffs, [c[1] - dy, c[0] - dx], order=3, prefilter=False,
                            mode="nearest")
        diff = np.abs(a - b)
        if exclude is not None:
            diff = diff[~(excluded(c[0] + dx, c[1] + dy) | excluded(c[0] - dx, c[1] - dy))]
        if diff.size < 8:
            return math.inf
        # trimmed: the most asymmetric half are hair or follicles, whatever c is
        keep = diff.size // 2
        return float(np.partition(diff, keep)[:keep].mean())

    # the trimmed asymmetry of a flat-topped spot has plateaus far from its minimum:
    # whole pixels around the start first, compared within ENTRY_GRID_RADIUS_PX
    reach = ENTRY_GRID_PX if exclude is None else ENTRY_REFINE_GRID_PX
    dx, dy = offsets(min(ENTRY_GRID_RADIUS_PX, radius_px))
    grid = [np.asarray(start) + np.array([i, j]) for j in range(-reach, reach + 1)
            for i in range(-reach, reach + 1) if i * i + j * j <= reach * reach]
    best = min(grid, key=asymmetry)
    dx, dy = offsets(radius_px)
    res = minimize(asymmetry, best, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-12, "initial_simplex":
                            best + np.array([[0, 0], [0.5, 0], [0, 0.5]])})
    cx, cy = float(res.x[0]), float(res.x[1])
    if np.hypot(cx - best[0], cy - best[1]) > max(3.0, 0.25 * radius_px):
        return float(best[0]), float(best[1])  # wandered off: keep the grid's (+-0.5 px)
    return cx, cy


CORE_WINDOW_PX = 12.0
"""The core model is fitted on the pixels within this distance of the entry point: three
standard deviations of the narrowest skin scattering at 0.04 mm pixels, where the
pixel's area changes a ring's value by more than 0.1%."""
CORE_INNER_PX = 3.0
"""Within this radius of the entry point the profile's samples are the core model's
means over rings every :data:`CORE_STEP_PX` wide (rings of a few pixels hold no
statistics); beyond it, ring medians corrected by the model for the pixel's area."""
CORE_STEP_PX = 0.25
CORE_SIGMA_RATIO = 1.15
CORE_MIN_SIGMA_PX = 0.35
"""The core model's Gaussians: standard deviations from CORE_MIN_SIGMA_PX up to four
window radii, each CORE_SIGMA_RATIO times the last (measured on the forehead's observed
profile with 0.04 mm pixels, noise-free: the point values within 0.1% in the inner 3
px, 0.6% with a ratio of 1.25; the corrected rings within 0.05%)."""
CORE_OUTLIER_RATIO = 0.7
"""Pixels darker than this share of the core model are left out of its fit (hair and
follicles darken; nothing in a spot brightens)."""
CORE_MAX_SHIFT_PX = 1.5
"""The fit refines the entry point by at most this much from where it started (the
centre of symmetry, within 0.07 px on the simulator, hair included); a flat-topped
spot's chi^2 is shallow, and a strand beside it can pull the minimum away."""


@dataclass(frozen=True)
class CoreModel:
    """The spot near the entry point as a non-negative sum of normalised 2D Gaussians
    sum_k a_k G(s_k), fitted to the pixels as each pixel records it (the Gaussian's mean
    over the pixel's square, a product of two differences of normal CDFs). Evaluated at
    points it is the profile with the pixel's area integration undone."""

    centre_px: tuple[float, float]
    sigmas_px: NDArray[np.float64]
    weights: NDArray[np.float64]
    """(K, C): per pixel^2 area, in the image's units."""
    covariance: NDArray[np.float64]
    """(C, K, K) of the weights (zero outside each channel's active set)."""
    window_px: float
    outliers: int
    """Pixels left out of the fit as dark outliers."""

    def at_points(self, radius_px: NDArray[np.float64]) -> NDArray[np.float64]:
        """The model at radii (px) from its centre: (n, C)."""
        return _point_basis(radius_px, self.sigmas_px) @ self.weights

    def ring_means(self, inner_px: NDArray[np.float64], outer_px: NDArray[np.float64]
                   ) -> NDArray[np.float64]:
        """The model's mean over the rings between ``inner_px`` and ``outer_px``: (n, C).
        A normalised 2D Gaussian puts exp(-a^2 / 2s^2) - exp(-b^2 / 2s^2) of its light
        between radii a and b."""
        a = np.asarray(inner_px, dtype=np.float64).reshape(-1, 1)
        b = np.asarray(outer_px, dtype=np.float64).reshape(-1, 1)
        s2 = 2.0 * self.sigmas_px**2
        share = np.exp(-a * a / s2) - np.exp(-b * b / s2)
        return (share / (math.pi * (b * b - a * a))) @ self.weights

    def std_at_points(self, radius_px: NDArray[np.float64]) -> NDArray[np.float64]:
        """Standard deviation of :meth:`at_points` from the weights' covariance."""
        basis = _point_basis(radius_px, self.sigmas_px)
        return np.sqrt(np.maximum(np.einsum("nk,ckl,nl->nc", basis, self.covariance, basis),
                                  0.0))

    def pixel_means(self, xs: NDArray[np.float64], ys: NDArray[np.float64]
                    ) -> NDArray[np.float64]:
        """The model as the pixels centred at (xs, ys) record it: (n, C)."""
        return _pixel_basis(xs - self.centre_px[0], ys - self.centre_px[1],
                            self.sigmas_px) @ self.weights


def _point_basis(radius_px: NDArray[np.float64], sigmas: NDArray[np.float64]
                 ) -> NDArray[np.float64]:
    r = np.asarray(radius_px, dtype=np.float64).reshape(-1, 1)
    return np.exp(-0.5 * (r / sigmas) ** 2) / (2.0 * math.pi * sigmas**2)


def _pixel_basis(dx: NDArray[np.float64], dy: NDArray[np.float64],
                 sigmas: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mean of each normalised 2D Gaussian over the unit pixels at offsets (dx, dy): a
    product of two 1D pixel integrals, each made once per distinct column and row."""
    def axis(d: NDArray[np.float64]) -> NDArray[np.float64]:
        values, index = np.unique(d, return_inverse=True)
        g = special.ndtr((values[:, None] + 0.5) / sigmas) - \
            special.ndtr((values[:, None] - 0.5) / sigmas)
        return g[index.reshape(-1)]

    return axis(dx) * axis(dy)


def _core_weights(image: NDArray[np.float64], variance: NDArray[np.float64] | None
                  ) -> NDArray[np.float64]:
    """Per pixel and channel 1 / standard deviation: the merge's noise, else (no noise
    model) 1% of the value with a floor of 0.1% of the peak."""
    if variance is not None:
        return 1.0 / np.sqrt(np.maximum(variance, 1e-300))
    return 1.0 / (0.01 * np.abs(image) + 1e-3 * np.abs(image).max(axis=0) + 1e-300)


def _nnls_channels(a: NDArray[np.float64], b: NDArray[np.float64],
                   w: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """NNLS per channel of (a * w) x = b * w; the weights (K, C) and the summed chi^2."""
    from scipy.optimize import nnls  # lazy: 0.50 s to import

    weights = np.zeros((a.shape[1], b.shape[1]))
    chi2 = 0.0
    for c in range(b.shape[1]):
        aw = a * w[:, c:c + 1]
        norm = np.maximum(np.linalg.norm(aw, axis=0), 1e-300)  # unit columns: better posed
        x, rnorm = nnls(aw / norm, b[:, c] * w[:, c], maxiter=50 * a.shape[1])
        weights[:, c] = x / norm
        chi2 += rnorm * rnorm
    return weights, chi2


def fit_core_model(image: NDArray[np.float64], variance: NDArray[np.float64] | None,
                   centre_px: tuple[float, float], exclude: NDArray[np.bool_] | None = None,
                   window_px: float = CORE_WINDOW_PX, refine_centre: bool = True
                   ) -> CoreModel:
    """Fit a :class:`CoreModel` to the pixels within ``window_px`` of ``centre_px``
    (less ``exclude`` and non-finite ones), each weighted by its noise: per channel a
    non-negative least squares (Lawson & Hanson) on the pixel-integrated Gaussians; the
    centre refined by minimising the summed chi^2 over it (Nelder-Mead, the weights
    re-solved at each step: variable projection; within CORE_MAX_SHIFT_PX of the
    start), once the first fit has found the dark outliers (below CORE_OUTLIER_RATIO of
    the model), which are left out; repeated until they settle (four fits at most)."""
    from scipy.optimize import minimize  # lazy: 0.50 s to import

    h, w, channels = image.shape
    cx0, cy0 = centre_px
    half = math.ceil(window_px)
    ys = np.arange(max(0, round(cy0) - half), min(h, round(cy0) + half + 1))
    xs = np.arange(max(0, round(cx0) - half), min(w, round(cx0) + half + 1))
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    sel = np.hypot(xx - cx0, yy - cy0) <= window_px
    if exclude is not None:
        sel &= ~exclude[yy, xx]
    px, py = xx[sel].astype(np.float64), yy[sel].astype(np.float64)
    values = image[py.astype(int), px.astype(int)].astype(np.float64)
    wts = _core_weights(values, None if variance is None else
                        variance[py.astype(int), px.astype(int)])
    finite = np.isfinite(values).all(axis=1) & np.isfinite(wts).all(axis=1)
    sigmas = CORE_MIN_SIGMA_PX * CORE_SIGMA_RATIO ** np.arange(
        int(math.log(4.0 * window_px / CORE_MIN_SIGMA_PX) / math.log(CORE_SIGMA_RATIO)) + 1)
    keep = finite.copy()
    if keep.sum() < 2 * sigmas.size:
        raise InputError(f"too few usable pixels ({int(keep.sum())}) within {window_px:g} px of "
                         f"the entry point ({cx0:.1f}, {cy0:.1f}) to model the core")

    def chi2_at(c: NDArray[np.float64]) -> float:
        basis = _pixel_basis(px[keep] - c[0], py[keep] - c[1], sigmas)
        return _nnls_channels(basis, values[keep], wts[keep])[1]

    centre = np.array([cx0, cy0], dtype=np.float64)
    step = 0.3  # px: the first simplex; later passes start where the last one ended
    for it in range(4):
        if refine_centre and it > 0:  # once the first fit has found the dark outliers
            res = minimize(chi2_at, centre, method="Nelder-Mead",
                           options={"xatol": 2e-3, "fatol": 1e-6, "initial_simplex":
                                    centre + np.array([[0.0, 0.0], [step, 0.0], [0.0, step]])})
            if np.hypot(*(res.x - np.array([cx0, cy0]))) <= CORE_MAX_SHIFT_PX:
                centre = res.x
            step = 0.05
        basis_all = _pixel_basis(px - centre[0], py - centre[1], sigmas)
        weights, _ = _nnls_channels(basis_all[keep], values[keep], wts[keep])
        model = basis_all @ weights
        dark = finite & np.any(values < CORE_OUTLIER_RATIO * model, axis=1)
        new_keep = finite & ~dark
        if (it > 0 and np.array_equal(new_keep, keep)) or new_keep.sum() < 2 * sigmas.size:
            break
        keep = new_keep
    basis = basis_all[keep]
    resid = (values[keep] - basis @ weights) * wts[keep]
    dof = max(int(keep.sum()) - sigmas.size, 1)
    cov = np.zeros((channels, sigmas.size, sigmas.size))
    for c in range(channels):
        active = weights[:, c] > 0
        a = basis[:, active] * wts[keep][:, c:c + 1]
        scale = max(1.0, float(resid[:, c] @ resid[:, c]) / dof)  # model error, if larger
        cov[c][np.ix_(active, active)] = np.linalg.pinv(a.T @ a) * scale
    return CoreModel((float(centre[0]), float(centre[1])), sigmas, weights, cov, window_px,
                     int(finite.sum() - keep.sum()))


def radial_profile(
    hdr: FloatImage,
    centre_px: tuple[float, float],
    mm_per_pixel: float,
    ring_width_px: float = 1.0,
    max_radius_mm: float | None = None,
    mode: ProfileMode = "rings",
    variance: NDArray[np.float64] | None = None,
    exclude: NDArray[np.bool_] | None = None,
    core: CoreModel | None = None,
) -> MeasuredProfile:
    """The radial profile around ``centre_px`` with per-sample standard errors.

    ``rings``: the median over each ring of width ``ring_width_px`` (robust to hair and
    follicle shadows), at the ring's median pixel distance; standard error from the
    median absolute deviation (1.2533 * 1.4826 MAD / sqrt(n)), and no smaller than what
    the sensor's noise alone gives (``variance``, per pixel: sqrt(pi/2 sum var) / n, the
    median's efficiency); without ``variance``, no smaller than 1% of the value. Pixels
    in ``exclude`` (hair, :func:`hair_mask`) are left out of the rings. With a
    :class:`CoreModel` (its centre is then the entry point), the samples within
    CORE_INNER_PX are the model's values at points every CORE_STEP_PX (with the
    standard deviation its fit gives them), and within the model's window each ring is
    the median of its pixels over the model as they record it, times the model at the
    ring's radius (the pixel's area and the profile's slope across the ring undone, in
    the value and in the spread).
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
    first = 0 if core is None else math.ceil(CORE_INNER_PX / ring_width_px - 1e-9)
    keep = (ring < n_rings) & (ring >= first)
    if exclude is not None:
        keep &= ~exclude.ravel()
    flat = np.flatnonzero(keep)
    ring, dist = ring[flat], dist[flat]
    pix = hdr.reshape(-1, 3)[flat].astype(np.float64)
    var = None if variance is None else variance.reshape(-1, 3)[flat]
    order = np.argsort(ring, kind="stable")
    ring, dist, pix, flat = ring[order], dist[order], pix[order], flat[order]
    var = None if var is None else var[order]
    bounds = np.searchsorted(ring, np.arange(n_rings + 1))
    radii = np.full(n_rings, np.nan)
    values = np.full((n_rings, 3), np.nan)
    stderr = np.full((n_rings, 3), np.nan)
    for i in range(first, n_rings):
        a, b = bounds[i], bounds[i + 1]
        if b <= a:
            continue
        seg = pix[a:b]
        radii[i] = float(np.median(dist[a:b]))
        # within the core model's window the pixels are taken relative to the model as
        # each records it (the profile's slope across the ring and the pixel's area
        # undone), and the ring's value is that median ratio at the model's point value
        scale = np.ones(3)
        if core is not None and radii[i] < core.window_px - 1.0:
            model = core.pixel_means((flat[a:b] % w).astype(np.float64),
                                     (flat[a:b] // w).astype(np.float64))
            if np.all(model > 0):
                seg = seg / model
                scale = core.at_points(np.array([radii[i]]))[0]
        med = np.median(seg, axis=0)
        mad = np.median(np.abs(seg - med), axis=0)
        values[i] = med * scale
        stderr[i] = 1.2533 * 1.4826 * mad / math.sqrt(b - a) * scale
        if var is not None:
            stderr[i] = np.maximum(stderr[i], np.sqrt(0.5 * math.pi * var[a:b].sum(axis=0))
                                   / (b - a))
    ok = np.isfinite(values).all(axis=1) & np.isfinite(radii)
    if var is not None:
        ok &= np.isfinite(stderr).all(axis=1)
    radii, values, stderr = radii[ok], values[ok], stderr[ok]
    if core is not None:
        inner = np.arange(0.0, CORE_INNER_PX - 1e-9, CORE_STEP_PX)
        inner = inner[inner < (radii[0] if radii.size else CORE_INNER_PX)]
        # each a ring mean, as every sample of a profile is read (the fit's energy, the
        # edge): the point values of a sharp spike summed as rings miscount its light
        edges = np.concatenate([[0.0], 0.5 * (inner[1:] + inner[:-1]),
                                [0.5 * (inner[-1] + (radii[0] if radii.size
                                                     else inner[-1] + CORE_STEP_PX))]])
        means = core.ring_means(edges[:-1], edges[1:])
        radii = np.concatenate([inner, radii])
        values = np.concatenate([means, values])
        stderr = np.concatenate([core.std_at_points(inner), stderr])
    if var is not None:
        return MeasuredProfile(radii * mm_per_pixel, values, stderr)
    return MeasuredProfile(radii * mm_per_pixel, values, _floor_std(stderr, values))


def ring_pixel_noise(variance: NDArray[np.float64], centre_px: tuple[float, float],
                     radius_px: NDArray[np.float64], ring_width_px: float = 1.0
                     ) -> NDArray[np.float64]:
    """One pixel's noise (standard deviation, per channel) on each ring of radius
    ``radius_px`` around ``centre_px``: the square root of the median of the merge's
    per-pixel variance over the ring's pixels (inf where a ring has none)."""
    h, w, c = variance.shape
    yy, xx = np.mgrid[0:h, 0:w]
    ring = np.floor(np.hypot(xx - centre_px[0], yy - centre_px[1]).ravel() / ring_width_px
                    + 0.5).astype(np.int64)
    flat = variance.reshape(-1, c)
    order = np.argsort(ring, kind="stable")
    bounds = np.searchsorted(ring[order], np.arange(ring.max() + 2))
    out = np.full((radius_px.size, c), np.inf)
    for i, r in enumerate(radius_px):
        k = math.floor(r / ring_width_px + 0.5)
        if k + 1 < bounds.size and bounds[k + 1] > bounds[k]:
            out[i] = np.sqrt(np.median(flat[order[bounds[k]:bounds[k + 1]]], axis=0))
    return out


HAIR_RATIO = 0.6
"""A pixel darker than this share of the radial model at its radius (3 x 3 median of
the ratio: a strand is 1.5-3 px wide) is hair; the paper's strands pass 10-50% of the
light."""
HAIR_CORE_PX = 3.0
HAIR_CORE_LIMIT = 0.5
HAIR_ENTRY_PX = 1.0
SPIKE_REACH_PX = 3.0
"""How far from the centre a sharp entry spike (light within a pixel) leaves its
neighbours off any smooth radial model: a dark patch confined within it is no strand
(strands are 1.5-3 px wide lines across the spot)."""
"""A capture with hair within HAIR_ENTRY_PX of its entry point (a strand over it), or
whose core (within HAIR_CORE_PX of it) is more than HAIR_CORE_LIMIT hair, is refused:
the paper re-shot such spots. A strand whose edge passes 3 px or more from the entry
point leaves the mask (grown by a pixel) at least 1.5 px away, covers 15-40% of the
core and is masked."""


HAIR_RAW_SIGMAS = 25.0
"""Where the radial model stands this many noise sigmas above zero, a pixel's own ratio
to it decides (HAIR_RATIO is then 10 sigmas down): the 3 x 3 median that guards dimmer
pixels against noise erases a strand one or two pixels wide, as it did over the entry
point in 2 of 180 simulated spots."""


def hair_mask(hdr: FloatImage, centre_px: tuple[float, float], profile_px: MeasuredProfile,
              variance: NDArray[np.float64] | None = None) -> NDArray[np.bool_]:
    """Hair strands as dark outliers against the radial model: pixels whose luminance is
    below HAIR_RATIO of the profile at their radius, where the model stands 10 noise
    sigmas above zero (or, without a noise model, above 1% of its peak): the pixel's own
    ratio where the model stands HAIR_RAW_SIGMAS above zero (no noise model: 5% of its
    peak), the 3 x 3 median of the ratio elsewhere; grown by one pixel for the strands'
    edges. ``profile_px``: radii in px. Strands are lines: dark pixels that reach no
    farther than :data:`SPIKE_REACH_PX` from the centre are not hair but a sharp entry
    spike's neighbours (single scattering puts much of the light inside the centre
    pixels, and no smooth radial model stands right beside it)."""
    h, w, _ = hdr.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - centre_px[0], yy - centre_px[1])
    lum = hdr.astype(np.float64).sum(axis=2)
    model = np.interp(r, profile_px.radius_mm, profile_px.values.sum(axis=1), right=np.nan)
    raw = lum / np.where(model > 0, model, np.nan)
    smooth = median_filter(raw, size=3, mode="nearest")
    if variance is not None:
        sigma = np.sqrt(np.where(np.isfinite(variance), variance, np.inf).sum(axis=2))
        trusted, bright = model > 10.0 * sigma, model > HAIR_RAW_SIGMAS * sigma
    else:
        trusted, bright = model > 0.01 * np.nanmax(model), model > 0.05 * np.nanmax(model)
    dark = trusted & (np.where(bright, raw, smooth) < HAIR_RATIO)
    labels, count = label(dark, structure=np.ones((3, 3)))
    if count:
        reach = np.zeros(count + 1)
        np.maximum.at(reach, labels[dark], r[dark])
        dark &= reach[labels] > SPIKE_REACH_PX
    grown = dark.copy()
    grown[1:] |= dark[:-1]
    grown[:-1] |= dark[1:]
    grown[:, 1:] |= dark[:, :-1]
    grown[:, :-1] |= dark[:, 1:]
    return grown


def hair_over_core(hair: NDArray[np.bool_], centre_px: tuple[float, float]
                   ) -> tuple[float, bool]:
    """The share of the core (within HAIR_CORE_PX of the entry point) that ``hair``
    covers, and whether it covers a pixel within HAIR_ENTRY_PX of the entry point."""
    yy, xx = np.mgrid[0:hair.shape[0], 0:hair.shape[1]]
    dist = np.hypot(xx - centre_px[0], yy - centre_px[1])
    return float(hair[dist <= HAIR_CORE_PX].mean()), bool(hair[dist <= HAIR_ENTRY_PX].any())


def _floor_std(stderr: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    # A ring of one or two pixels has no spread to measure: assume 1% of the value.
    floor = 0.01 * np.abs(values) + 1e-12 * np.abs(values).max()
    return np.maximum(stderr, floor)
