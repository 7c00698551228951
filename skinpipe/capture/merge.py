"""HDR merging of bracketed exposures (ingest, step 1): noise-optimal for linear sensors.

Granados et al. 2010 ("Optimal HDR reconstruction with linear digital cameras") and
Hasinoff et al. 2010 for linear integer captures; Debevec & Malik 1997's hat weights
(colour-hdri) for non-linear ones. See docs/ingest.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any, Literal

import numpy as np
from colour_hdri import weighting_function_Debevec1997
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from ..errors import InputError
from ..imageio import ACESCG, LoadedImage, convert_colorspace

FloatImage = NDArray[np.float32]
MergeMethod = Literal["optimal", "hat"]


def _is_scene_linear(colorspace: str) -> bool:
    """Whether OCIO's transform from ``colorspace`` to ACEScg is linear (a matrix)."""
    probe = np.array([[[0.02, 0.3, 0.7], [0.04, 0.6, 1.4]]], np.float32)
    out = convert_colorspace(probe, colorspace, ACESCG).astype(np.float64)
    return bool(np.allclose(out[0, 1], 2 * out[0, 0], rtol=1e-4, atol=1e-7))


@dataclass(frozen=True)
class SensorNoise:
    """Noise of a linear sensor in code values (1 = full scale): a pixel that records c
    above the black level b has variance ``gain * (c - b) + read ** 2`` (shot noise:
    ``gain`` is one electron in code values; read noise ``read``)."""

    gain: float
    read: float
    source: str
    """"manifest", or "estimated" from the brackets themselves."""
    black: float = 0.0
    """The code value of no light (the sensor's offset, which keeps its noise from being
    clipped at zero)."""
    black_source: str = "estimated"


BLACK_MIN_PIXELS = 100
"""Fewer dim, unclipped pixel pairs than this leave the black level at the shortest
bracket's darkest percentile."""
BLACK_DIM_SIGNAL = 0.01
"""Pixels estimate the black level where their neighbours read below this above the
darkest percentile in the longer bracket: dim, so shot noise adds little to the read
noise there (3.5 read-noise sigmas at 1% of full scale on the simulator's sensor)."""


def _neighbour_mean(code: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mean of each pixel's 8 neighbours (edges repeated): its expected value
    without its own noise."""
    from scipy.ndimage import uniform_filter  # lazy: 0.25 s to import

    return (9.0 * uniform_filter(code, size=(3, 3, 1), mode="nearest") - code) / 8.0


def estimate_black_level(codes: list[NDArray[Any]], exposures_s: list[float],
                         clip_level: float = 0.98) -> float:
    """The sensor's black level b (the code of no light) from the brackets themselves.

    A sensor whose shortest bracket reads exactly 0 in its darkest percentile clips its
    noise at zero: it has no offset, b = 0. Otherwise, for consecutive exposures t1 < t2
    (ratio r) a linear sensor records c2 - b = r (c1 - b) on average, so over pixels
    clipped in neither, b = mean(r c1 - c2) / (r - 1) (gross outliers beyond 5 MADs
    left out). The pixels are the dim ones (:data:`BLACK_DIM_SIGNAL`, where the noise is
    mostly read noise and the mean is precise: about 1e-6 of full scale from the
    simulator's dark surround), chosen on their neighbours, never on their own noisy
    values (which favours pixels whose noise is up: b read 0.36 read-noise sigma high
    when chosen on c1)."""
    order = np.argsort(exposures_s)
    darkest = float(np.percentile(codes[order[0]], 1.0))
    if darkest <= 0.0:
        return 0.0
    num, count = 0.0, 0
    for a, c in pairwise(order):
        r = exposures_s[c] / exposures_s[a]
        if not r > 1.05:
            continue
        c1, c2 = codes[a].astype(np.float64), codes[c].astype(np.float64)
        ok = np.all((c1 < clip_level) & (c2 < clip_level), axis=2, keepdims=True)
        ok = ok & (_neighbour_mean(c2) < darkest + BLACK_DIM_SIGNAL)
        d = (r * c1 - c2)[ok] / (r - 1.0)
        if d.size:
            mad = float(np.median(np.abs(d - np.median(d))))
            d = d[np.abs(d - np.median(d)) <= 5.0 * 1.4826 * mad + 1e-12]
        num += float(d.sum())
        count += d.size
    if count < BLACK_MIN_PIXELS:
        return darkest
    return max(num / count, 0.0)


def estimate_sensor_noise(codes: list[NDArray[Any]], exposures_s: list[float],
                          clip_level: float = 0.98, black: float = 0.0) -> SensorNoise:
    """Shot and read noise from the brackets themselves (Granados et al. 2010, sec. 4):
    for consecutive exposures t1 < t2 (ratio r) the difference d = (c2 - b) - r (c1 - b)
    of a pixel unclipped in both has variance g mu2 (1 + r) + s^2 (1 + r^2), mu2 its
    expected code above the black level b in the longer one; a straight line through
    d's robust variance (MAD) in bins of mu2 gives the gain g and read noise s."""
    order = np.argsort(exposures_s)
    xs, ys, ws = [], [], []
    for a, b in pairwise(order):
        r = exposures_s[b] / exposures_s[a]
        c1, c2 = codes[a].astype(np.float64) - black, codes[b].astype(np.float64) - black
        ok = np.broadcast_to(np.all((c1 + black < clip_level) & (c2 + black < clip_level),
                                    axis=2, keepdims=True), c1.shape)
        mu2 = gaussian_filter(c2, sigma=(1.5, 1.5, 0))  # expected code, not the noisy one
        d = (c2 - r * c1)[ok]
        m = mu2[ok]
        if d.size < 200:
            continue
        edges = np.unique(np.quantile(m, np.linspace(0, 1, 21)))
        for lo, hi in pairwise(edges):
            sel = (m >= lo) & (m < hi)
            if sel.sum() < 50:
                continue
            dd = d[sel]
            mad = np.median(np.abs(dd - np.median(dd)))
            xs.append([max(float(np.median(m[sel])), 0.0) * (1 + r), 1 + r * r])
            ys.append((1.4826 * mad) ** 2)
            ws.append(float(sel.sum()))
    if len(ys) < 3:
        raise InputError("cannot estimate the sensor's noise from these brackets (too few "
                         "unclipped pixels in consecutive exposures): give "
                         "'sensor': {'full_well_e': ..., 'read_noise_e': ...} in capture.json")
    x, y, w = np.asarray(xs), np.asarray(ys), np.sqrt(np.asarray(ws))
    (gain, read2), *_ = np.linalg.lstsq(x * w[:, None], y * w, rcond=None)
    return SensorNoise(max(float(gain), 1e-12), math.sqrt(max(float(read2), 1e-16)),
                       "estimated", black)


@dataclass(frozen=True)
class MergedExposures:
    """A merge's result: the scene-linear radiance per second in ``space`` (the camera's
    own linear space for linear captures, whose channels the profile is read in; ACEScg
    for the rest), the pixels no bracket resolved, and for a noise-optimal merge its
    per-pixel variance (``space``, per second^2; inf where unresolved) and the noise
    model it used."""

    radiance: NDArray[np.float64]
    space: str
    unresolved: NDArray[np.bool_]
    variance: NDArray[np.float64] | None = None
    noise: SensorNoise | None = None

    @property
    def hdr(self) -> FloatImage:
        """The merged image in ACEScg (radiance per second), as ingest writes it."""
        if self.space == ACESCG:
            return self.radiance.astype(np.float32)
        return convert_colorspace(self.radiance.astype(np.float32), self.space,
                                  ACESCG).astype(np.float32)


def merge_exposures(
    images: list[LoadedImage],
    exposures_s: list[float],
    colorspace: str,
    noise_floor: float | None = None,
    clip_level: float = 0.98,
    noise: SensorNoise | None = None,
    method: MergeMethod = "optimal",
) -> MergedExposures:
    """Merge exposures into one scene-linear HDR image (radiance per second).

    Linear integer captures: each unclipped bracket's radiance (c - b) / t above the
    black level b, weighted by its inverse variance t^2 / (g mu t + s^2) from the
    sensor's noise (``noise``, else estimated from the brackets,
    :func:`estimate_black_level` and :func:`estimate_sensor_noise`), evaluated on a
    smoothed estimate mu of the radiance, never on the pixel's own noisy value
    (Granados et al. 2010, "Optimal HDR reconstruction with linear digital cameras";
    Hasinoff et al. 2010): a weight that follows the noisy value picks the short
    brackets' upward noise in the dark and biases the flux. The only hard cut is
    saturation; a pixel clipped in any channel is not used from that bracket. Merged and
    returned in the camera's space; the merge's variance is 1 / the sum of the weights.
    Non-linear (8-bit sRGB) captures keep Debevec & Malik 1997's hat weights
    (colour-hdri) times t, each bracket converted to ACEScg first, as every capture does
    with ``method="hat"``.
    """
    linear = all(not img.is_float for img in images) and _is_scene_linear(colorspace)
    if method == "optimal" and linear:
        return _merge_noise_optimal(images, exposures_s, colorspace, clip_level, noise)
    black = 0.0
    if linear:  # the hat weights, on codes above the same black level
        black = noise.black if noise is not None and noise.black_source == "manifest" else \
            estimate_black_level([i.pixels for i in images], exposures_s, clip_level)
    hdr, unresolved = _merge_hat(images, exposures_s, colorspace, noise_floor, clip_level,
                                 black)
    return MergedExposures(hdr.astype(np.float64), ACESCG, unresolved)


def _merge_noise_optimal(images: list[LoadedImage], exposures_s: list[float],
                         colorspace: str, clip_level: float, noise: SensorNoise | None
                         ) -> MergedExposures:
    raw = [img.pixels.astype(np.float64) for img in images]
    t = np.asarray(exposures_s, np.float64)
    single = len(raw) == 1  # one bracket: its weights cancel, no noise model is needed
    if noise is None and not single:
        black = estimate_black_level(raw, exposures_s, clip_level)
        noise = estimate_sensor_noise(raw, exposures_s, clip_level, black)
    elif noise is not None and noise.black_source == "estimated" and not single:
        noise = replace(noise, black=estimate_black_level(raw, exposures_s, clip_level))
    model = noise or SensorNoise(1.0, 1.0, "not needed (one bracket)", 0.0, "none")
    valid = [~np.any(c >= clip_level, axis=2, keepdims=True) for c in raw]
    codes = [c - model.black for c in raw]
    # first estimate: the longest unclipped bracket at each pixel
    mu = np.zeros_like(codes[0])
    for i in np.argsort(t):
        mu = np.where(valid[i], codes[i] / t[i], mu)
    for _ in range(2):
        weights = _inverse_variance_weights(mu, t, valid, model)
        num = sum(w * c / ti for w, c, ti in zip(weights, codes, t, strict=True))
        den = sum(weights)
        resolved = den > 0
        mu = np.where(resolved, num / np.where(resolved, den, 1.0), mu)
    shortest = int(np.argmin(t))
    mu = np.where(resolved, mu, codes[shortest] / t[shortest])  # clipped everywhere
    variance = None
    if not single:
        with np.errstate(divide="ignore"):
            variance = np.where(resolved, 1.0 / np.where(resolved, den, 1.0), np.inf)
    return MergedExposures(mu, colorspace, ~np.all(resolved, axis=2), variance, noise)


def _inverse_variance_weights(mu: NDArray[np.float64], t: NDArray[np.float64],
                              valid: list[NDArray[np.bool_]], noise: SensorNoise
                              ) -> list[NDArray[np.float64]]:
    """Each bracket's weight t^2 / (g mu t + s^2) (zero where clipped), the inverse
    variance of its radiance estimate (c - b) / t, on a smoothed radiance estimate
    ``mu`` (camera space, code values per second above the black level)."""
    smooth = gaussian_filter(np.maximum(mu, 0.0), sigma=(1.0, 1.0, 0))
    return [ok * ti * ti / (noise.gain * smooth * ti + noise.read ** 2)
            for ti, ok in zip(t, valid, strict=True)]


def _merge_hat(images: list[LoadedImage], exposures_s: list[float], colorspace: str,
               noise_floor: float | None, clip_level: float, black: float = 0.0
               ) -> tuple[FloatImage, NDArray[np.bool_]]:
    """Debevec & Malik 1997 weighting (colour-hdri's hat function, zero at the noise
    floor and at clipping) times the exposure time (Robertson et al. 2003); radiance
    from the codes less the black level ``black`` (linear captures)."""
    floor = black + (noise_floor if noise_floor is not None else
                     (2.0 / 255.0 if images[0].bits == 8 else 2e-4))
    num = np.zeros(images[0].pixels.shape, dtype=np.float64)
    den = np.zeros_like(num)
    radiance = []  # per bracket, ACEScg per second
    for img, t in zip(images, exposures_s, strict=True):
        code = img.pixels
        if img.is_float:
            weight = np.ones_like(code, dtype=np.float64)
        else:
            weight = weighting_function_Debevec1997(code, domain_l=floor, domain_h=clip_level)
            clipped = np.any(code >= clip_level, axis=2, keepdims=True)
            weight = np.where(clipped, 0.0, weight)
        radiance.append(convert_colorspace(code - np.float32(black), colorspace,
                                           ACESCG).astype(np.float64) / t)
        num += weight * t * radiance[-1]
        den += weight * t
    resolved = den > 0
    # Unresolved pixels: below the floor in every bracket -> the longest exposure's value;
    # clipped in every bracket -> the shortest exposure's (a lower bound).
    longest = int(np.argmax(exposures_s))
    shortest = int(np.argmin(exposures_s))
    bright = np.any(images[shortest].pixels >= clip_level, axis=2, keepdims=True)
    fallback = np.where(bright, radiance[shortest], radiance[longest])
    hdr = np.where(resolved, num / np.where(resolved, den, 1.0), fallback)
    return hdr.astype(np.float32), ~np.all(resolved, axis=2)
