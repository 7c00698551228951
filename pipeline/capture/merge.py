"""HDR merging of bracketed exposures (ingest, step 1): noise-optimal for linear sensors.

Granados et al. 2010 ("Optimal HDR reconstruction with linear digital cameras") and
Hasinoff et al. 2010 for linear integer captures; Debevec & Malik 1997's hat weights
(colour-hdri) for non-linear ones. See docs/ingest.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np
from colour_hdri import weighting_function_Debevec1997
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from ..errors import InputError
from ..imageio import ACESCG, LoadedImage, colorspace_matrix, convert_colorspace

FloatImage = NDArray[np.float32]


def _is_scene_linear(colorspace: str) -> bool:
    """Whether OCIO's transform from ``colorspace`` to ACEScg is linear (a matrix)."""
    probe = np.array([[[0.02, 0.3, 0.7], [0.04, 0.6, 1.4]]], np.float32)
    out = convert_colorspace(probe, colorspace, ACESCG).astype(np.float64)
    return bool(np.allclose(out[0, 1], 2 * out[0, 0], rtol=1e-4, atol=1e-7))


@dataclass(frozen=True)
class SensorNoise:
    """Noise of a linear sensor in code values (1 = full scale): a pixel that records c
    has variance ``gain * c + read ** 2`` (shot noise: ``gain`` is one electron in
    code values; read noise ``read``)."""

    gain: float
    read: float
    source: str
    """"manifest", or "estimated" from the brackets themselves."""


def estimate_sensor_noise(codes: list[NDArray[Any]], exposures_s: list[float],
                          clip_level: float = 0.98) -> SensorNoise:
    """Shot and read noise from the brackets themselves (Granados et al. 2010, sec. 4):
    for consecutive exposures t1 < t2 (ratio r) the difference d = c2 - r c1 of a pixel
    unclipped in both has variance g mu2 (1 + r) + s^2 (1 + r^2), mu2 its expected code
    in the longer one; a straight line through d's robust variance (MAD) in bins of
    mu2 gives the gain g and read noise s."""
    order = np.argsort(exposures_s)
    xs, ys, ws = [], [], []
    for a, b in pairwise(order):
        r = exposures_s[b] / exposures_s[a]
        c1, c2 = codes[a].astype(np.float64), codes[b].astype(np.float64)
        ok = (c1 < clip_level) & (c2 < clip_level)
        ok &= np.all(c2 < clip_level, axis=2, keepdims=True) & \
            np.all(c1 < clip_level, axis=2, keepdims=True)
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
            xs.append([float(np.median(m[sel])) * (1 + r), 1 + r * r])
            ys.append((1.4826 * mad) ** 2)
            ws.append(float(sel.sum()))
    if len(ys) < 3:
        raise InputError("cannot estimate the sensor's noise from these brackets (too few "
                         "unclipped pixels in consecutive exposures): give "
                         "'sensor': {'full_well_e': ..., 'read_noise_e': ...} in capture.json")
    x, y, w = np.asarray(xs), np.asarray(ys), np.sqrt(np.asarray(ws))
    (gain, read2), *_ = np.linalg.lstsq(x * w[:, None], y * w, rcond=None)
    return SensorNoise(max(float(gain), 1e-12), math.sqrt(max(float(read2), 1e-16)),
                       "estimated")


@dataclass(frozen=True)
class MergedExposures:
    """A merge's result: the ACEScg image (radiance per second), the pixels no bracket
    resolved, and for a noise-optimal merge its per-pixel variance (ACEScg, per
    second^2; inf where unresolved) and the noise model it used."""

    hdr: FloatImage
    unresolved: NDArray[np.bool_]
    variance: NDArray[np.float64] | None = None
    noise: SensorNoise | None = None


def merge_exposures(
    images: list[LoadedImage],
    exposures_s: list[float],
    colorspace: str,
    noise_floor: float | None = None,
    clip_level: float = 0.98,
    noise: SensorNoise | None = None,
) -> MergedExposures:
    """Merge exposures into one scene-linear ACEScg HDR image (radiance per second).

    Linear integer captures: each unclipped bracket's radiance c / t weighted by its
    inverse variance t^2 / (g mu t + s^2) from the sensor's noise (``noise``, else
    estimated from the brackets, :func:`estimate_sensor_noise`), evaluated on a smoothed
    estimate mu of the radiance, never on the pixel's own noisy value (Granados et al.
    2010, "Optimal HDR reconstruction with linear digital cameras"; Hasinoff et al.
    2010): a weight that follows the noisy value picks the short brackets' upward noise
    in the dark and biases the flux. The only hard cut is saturation; a pixel clipped
    in any channel is not used from that bracket. Merged in the camera's space, then
    converted; the merge's variance is 1 / the sum of the weights, carried through the
    colour matrix with independent channels (var' = (M o M) var). Non-linear (8-bit
    sRGB) captures keep Debevec & Malik 1997's hat weights (colour-hdri) times t.
    """
    if all(not img.is_float for img in images) and _is_scene_linear(colorspace):
        return _merge_noise_optimal(images, exposures_s, colorspace, clip_level, noise)
    return MergedExposures(*_merge_hat(images, exposures_s, colorspace, noise_floor,
                                       clip_level))


def _merge_noise_optimal(images: list[LoadedImage], exposures_s: list[float],
                         colorspace: str, clip_level: float, noise: SensorNoise | None
                         ) -> MergedExposures:
    codes = [img.pixels.astype(np.float64) for img in images]
    t = np.asarray(exposures_s, np.float64)
    single = len(codes) == 1  # one bracket: its weights cancel, no noise model is needed
    if noise is None and not single:
        noise = estimate_sensor_noise(codes, exposures_s, clip_level)
    model = noise or SensorNoise(1.0, 1.0, "not needed (one bracket)")
    valid = [~np.any(c >= clip_level, axis=2, keepdims=True) for c in codes]
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
    hdr = convert_colorspace(mu.astype(np.float32), colorspace, ACESCG).astype(np.float32)
    variance = None
    if not single:
        m = colorspace_matrix(colorspace, ACESCG)
        with np.errstate(divide="ignore"):
            variance = np.where(resolved, 1.0 / np.where(resolved, den, 1.0), np.inf) @ \
                (m * m).T
    return MergedExposures(hdr, ~np.all(resolved, axis=2), variance, noise)


def _inverse_variance_weights(mu: NDArray[np.float64], t: NDArray[np.float64],
                              valid: list[NDArray[np.bool_]], noise: SensorNoise
                              ) -> list[NDArray[np.float64]]:
    """Each bracket's weight t^2 / (g mu t + s^2) (zero where clipped), the inverse
    variance of its radiance estimate c / t, on a smoothed radiance estimate ``mu``
    (camera space, code values per second)."""
    smooth = gaussian_filter(np.maximum(mu, 0.0), sigma=(1.0, 1.0, 0))
    return [ok * ti * ti / (noise.gain * smooth * ti + noise.read ** 2)
            for ti, ok in zip(t, valid, strict=True)]


def _merge_hat(images: list[LoadedImage], exposures_s: list[float], colorspace: str,
               noise_floor: float | None, clip_level: float
               ) -> tuple[FloatImage, NDArray[np.bool_]]:
    """Debevec & Malik 1997 weighting (colour-hdri's hat function, zero at the noise
    floor and at clipping) times the exposure time (Robertson et al. 2003)."""
    floor = noise_floor if noise_floor is not None else (2.0 / 255.0 if images[0].bits == 8
                                                         else 2e-4)
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
        radiance.append(convert_colorspace(code, colorspace, ACESCG).astype(np.float64) / t)
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
