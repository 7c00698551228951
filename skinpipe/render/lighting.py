"""Light transport at the skin's surface: irradiance per texel with Embree shadow rays,
and the Torrance-Sparrow specular lobe.

The paper (section 4) lights the texture-space irradiance map and shades specular with
Torrance-Sparrow (Beckmann distribution, roughness 0.35, rho_s 0.25). Light the
specular lobe reflects never enters the skin: irradiance is scaled by 1 - rho_dt(theta)
(the lobe's directional albedo, d'Eon & Luebke 2007, GPU Gems 3 ch. 14), and light
leaving towards the camera by 1 - rho_dt(theta_v).
"""

from __future__ import annotations

import math
import threading
import time
import zlib
from collections.abc import Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .bands import in_bands
from .kept import kept, source_of
from .opencl import (
    Kernel,
    build,
    cl_context,
    device_buffer,
    device_cache,
    host_buffer,
    host_output,
    jit_at_first_launch,
    read_output,
    run_on_host_arrays,
)
from .options import DEFAULT_RHO_S, DEFAULT_ROUGHNESS, INTERLEAVE_PERIODS
from .raytrace import (
    OFFSET_FLOAT_SCALE,
    OFFSET_INT_SCALE,
    OFFSET_ORIGIN,
    RayScene,
    morton_order,
)
from .scene import Light

SKIN_IOR = 1.4


def fresnel_schlick(cos_theta: NDArray[Any], ior: float = SKIN_IOR) -> NDArray[np.float64]:
    """Schlick's approximation of the dielectric Fresnel reflectance (Schlick 1994)."""
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def beckmann_ndf(cos_h: NDArray[Any], roughness: float) -> NDArray[np.float64]:
    """Beckmann microfacet distribution D(h), normalised so that int D cos_h dw = 1."""
    c = np.clip(np.asarray(cos_h, dtype=np.float64), 1e-6, 1.0)
    m2 = roughness * roughness
    tan2 = (1.0 - c * c) / (c * c)
    return np.exp(-tan2 / m2) / (math.pi * m2 * c ** 4)


def torrance_sparrow(n_dot_l: NDArray[Any], n_dot_v: NDArray[Any], n_dot_h: NDArray[Any],
                     v_dot_h: NDArray[Any], roughness: float = DEFAULT_ROUGHNESS,
                     rho_s: float = DEFAULT_RHO_S) -> NDArray[np.float64]:
    """Torrance-Sparrow BRDF rho_s D F G / (4 (n.l)(n.v)) (Torrance & Sparrow 1967; Cook &
    Torrance 1982's shadowing term G), zero below the horizon."""
    nl = np.asarray(n_dot_l, dtype=np.float64)
    nv = np.asarray(n_dot_v, dtype=np.float64)
    nh = np.asarray(n_dot_h, dtype=np.float64)
    vh = np.clip(np.asarray(v_dot_h, dtype=np.float64), 1e-6, 1.0)
    g = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
    ok = (nl > 0) & (nv > 0)
    denom = 4.0 * np.where(ok, nl * nv, 1.0)
    f = rho_s * beckmann_ndf(nh, roughness) * fresnel_schlick(vh) * g / denom
    return np.where(ok, f, 0.0)


def rho_dt_quadrature(roughness: float, rho_s: float, n: int = 64) -> NDArray[np.float64]:
    """rho_dt(cos theta) on n cosines from 0 to 1 by midpoint quadrature over the
    hemisphere of outgoing directions (polar 256 x azimuth 128) of
    :func:`torrance_sparrow` times cos theta_o: the lobe's directional albedo (d'Eon &
    Luebke 2007, GPU Gems 3 ch. 14, which tabulates it the same way)."""
    cos_in = np.linspace(0.0, 1.0, n)
    theta = (np.arange(256) + 0.5) / 256 * (math.pi / 2)
    phi = (np.arange(128) + 0.5) / 128 * math.pi  # symmetric in phi: integrate half, x2
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    out_dir = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    d_omega = np.sin(tt) * (math.pi / 2 / 256) * (math.pi / 128) * 2
    table = np.zeros(n)
    for i, c in enumerate(cos_in):
        if c <= 0:
            continue
        light = np.array([math.sqrt(max(0.0, 1 - c * c)), 0.0, c])
        h = out_dir + light
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        f = torrance_sparrow(c, out_dir[..., 2], h[..., 2], (out_dir * h).sum(-1),
                             roughness, rho_s)
        table[i] = float((f * out_dir[..., 2] * d_omega).sum())
    table[0] = table[1]
    return table


@lru_cache(maxsize=8)
def _rho_dt_table(roughness: float, rho_s: float, n: int = 64) -> NDArray[np.float64]:
    """:func:`rho_dt_quadrature`, kept in skinpipe's cache folder by numpy's version, the
    source of the functions that make it and the arguments: the quadrature was 0.2 s of
    the main thread before the rays in every render. Read-only: every caller shares it."""
    def read(doc: dict[str, Any]) -> NDArray[np.float64]:
        table = np.asarray(doc["table"], np.float64)
        if table.shape != (n,) or not np.all(np.isfinite(table) & (table >= 0)):
            raise ValueError("kept rho_dt table of another size or not finite")
        return table

    def make() -> tuple[NDArray[np.float64], dict[str, Any]]:
        table = rho_dt_quadrature(roughness, rho_s, n)
        return table, {"table": table.tolist()}  # repr: each float64 read back exactly

    source = source_of(rho_dt_quadrature, torrance_sparrow, beckmann_ndf, fresnel_schlick)
    table = kept("specular-albedo", "rho-dt", [np.__version__, source, roughness, rho_s, n],
                 read, make)
    table.setflags(write=False)
    return table


def specular_albedo(cos_theta: NDArray[Any], roughness: float = DEFAULT_ROUGHNESS,
                    rho_s: float = DEFAULT_RHO_S) -> NDArray[np.float64]:
    """rho_dt: the fraction of light arriving at cos_theta that the specular lobe
    reflects (so 1 - rho_dt enters the skin); linear in the table, in the precision of
    ``cos_theta`` (float32 stays float32: it runs per shadow-ray sample)."""
    c = np.asarray(cos_theta)
    dtype = np.dtype(np.float32 if c.dtype == np.float32 else np.float64)
    table = _rho_dt_table(float(roughness), float(rho_s)).astype(dtype)
    x = np.clip(c.astype(dtype, copy=False), 0, 1) * dtype.type(table.size - 1)
    i = np.minimum(x.astype(np.int32), table.size - 2)
    f = x - i.astype(dtype)
    return table[i] * (1 - f) + table[i + 1] * f


# --------------------------------------------------------------------------- sampling


def stratified_unit_square(n: int, rng: np.random.Generator,
                           multiple: int = 1) -> NDArray[np.float64]:
    """n jittered points in [0, 1)^2 on a near-square grid (n rounded up to a full grid
    whose numbers of rows and columns are multiples of ``multiple``). Point
    ``gy * nx + gx`` lies in column gx, row gy."""
    nx, ny = grid_shape(n, multiple)
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    pts = np.stack([(gx.ravel() + rng.random(nx * ny)) / nx,
                    (gy.ravel() + rng.random(nx * ny)) / ny], axis=1)
    return pts


def grid_shape(n: int, multiple: int = 1) -> tuple[int, int]:
    """Columns and rows of the stratified grid that holds at least n samples, each a
    multiple of ``multiple``."""
    nx = max(1, math.ceil(math.sqrt(n)))
    nx = -(-nx // multiple) * multiple
    ny = max(1, math.ceil(n / nx))
    return nx, -(-ny // multiple) * multiple


def interleaved_strata(n: int, period: int = 2) -> NDArray[np.int64]:
    """Interleaved sampling (Keller & Heidrich 2001) of a stratified grid whose rows and
    columns are multiples of the ``period`` p: row ``p (y % p) + (x % p)`` lists the
    strata that texel (x, y) traces, those whose column and row are the texel's modulo
    p. Each row is itself a coarser stratification of the square, and every p x p block
    of texels covers all the strata between them."""
    nx, ny = grid_shape(n, period)
    g = np.arange(nx * ny).reshape(ny, nx)
    return np.stack([g[qy::period, qx::period].ravel() for qy in range(period)
                     for qx in range(period)])


def interleave_period(texels_per_pixel: float, points: int, at_most: int = 0) -> int:
    """The interleaving period p for a texture of ``texels_per_pixel`` k texels across an
    image pixel at the skin and a light of ``points`` sample points: the largest of
    :data:`INTERLEAVE_PERIODS` that still casts every pixel at least ``points`` rays of
    the light (k^2 texels of points / p^2 rays each: p <= k) and whose p^2 classes each
    keep a sample (p^2 <= points); 2 when none does (a texture no finer than twice the
    image, or too few samples). Its reconstruction (the tent of
    :func:`filter_interleaved`, variance (p^2 - 1) / 6 texel^2 along each axis) is then
    narrower in pixels than period 2's at one texel a pixel (0.5 pixel^2). With
    ``at_most`` (a period asked for), the largest up to it whose classes each keep a
    sample, whatever the texels per pixel. At 4 texels a pixel (the demo face at texture
    4096) period 4 traces a quarter of period 2's rays, 16 a pixel and light at 16
    samples. The pixels' noise follows their rays: at 2.73 texels a pixel (texture 1024,
    384 x 384 pixels) period 4, which the reconstruction's width alone allowed (p^2 <=
    3 k^2 + 1), cast 7.5 rays a pixel and light and rendered the face's direct light in
    0.63 s at 1.45% error, period 2 in 0.84 s at 0.79% (error^2 x time 2.5x lower)."""
    k = float(texels_per_pixel)
    k2 = k * k if math.isfinite(k) and k > 0 else 0.0
    best = INTERLEAVE_PERIODS[0]
    for p in INTERLEAVE_PERIODS:
        narrow = p <= at_most if at_most else p * p <= k2
        if narrow and p * p <= points:
            best = p
    return best


def sobol_points(n: int) -> int:
    """The scrambled Sobol points :func:`light_sample_set` uses for ``n`` samples: n
    rounded up to a power of two (a Sobol set's balance holds for those)."""
    return 1 << max(0, math.ceil(math.log2(max(n, 1))))


def complement_sets(sets: NDArray[Any]) -> NDArray[Any]:
    """The strata each interleaving class does not trace (C, (C - 1) x count) for C
    classes (rows of ``sets``): for class c the sets of classes c + 1, ..., c + C - 1
    (mod C), in that order."""
    classes = sets.shape[0]
    return np.stack([np.concatenate([sets[(c + j) % classes] for j in range(1, classes)])
                     for c in range(classes)])


def light_sample_set(samples: int, rng: np.random.Generator, interleaved: bool,
                     sequence: str = "stratified", period: int = 2
                     ) -> tuple[NDArray[np.float64], NDArray[np.int64] | None]:
    """A light's sample points in [0, 1)^2 and, if ``interleaved``, the p^2 sets of them
    the interleaving classes of ``period`` p trace (rows, as :func:`interleaved_strata`);
    None where there are fewer points than classes.

    'stratified': a jittered near-square grid, each set the strata of one class of
    column and row modulo p. 'sobol': the first 2^m points of a scrambled Sobol sequence
    (Sobol 1967; scipy's linear matrix scrambling with a digital shift, Matousek 1998),
    each set a p^2-th of them in order: consecutive aligned blocks of a (0, m, 2)-net
    are nets themselves, so each set is stratified on its own as well."""
    if period not in INTERLEAVE_PERIODS:
        raise InputError(f"interleaving period must be one of {INTERLEAVE_PERIODS}, got "
                         f"{period}")
    classes = period * period
    if sequence == "sobol":
        m = sobol_points(samples)
        grid = scrambled_sobol(m, rng)
        sets = np.arange(m).reshape(classes, m // classes) if interleaved and \
            m >= classes else None
        return grid, sets
    if sequence != "stratified":
        raise InputError(f"unknown light sample sequence {sequence!r}")
    if interleaved and samples >= classes:
        return stratified_unit_square(samples, rng, period), \
            interleaved_strata(samples, period)
    return stratified_unit_square(samples, rng), None


def scrambled_sobol(m: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """The first ``m`` points (m, 2) of a scrambled 2-D Sobol sequence as scipy makes them
    (``qmc.Sobol(2, scramble=True, seed=rng).random(m)``: linear matrix scrambling and a
    digital shift, Matousek 1998), ``rng`` left in the state scipy leaves it in. Kept in
    skinpipe's cache folder by scipy's version, ``m`` and ``rng``'s state: importing
    scipy.stats for them took 0.6-0.9 s of CPU with the GIL held in every render, on the
    prewarm's thread beside the texture maps (0.76 -> 0.48 s at texture 4096 without
    it). A kept file that does not read back is made again; one that cannot be written
    is not kept."""
    import scipy

    def read(doc: dict[str, Any]) -> NDArray[np.float64]:
        points = np.asarray(doc["points"], np.float64).reshape(m, 2)
        if not np.all((points >= 0) & (points < 1)):
            raise ValueError("kept Sobol points outside the unit square")
        rng.bit_generator.state = doc["after"]
        return points

    def make() -> tuple[NDArray[np.float64], dict[str, Any]]:
        from scipy.stats import qmc  # lazy: all of scipy.stats comes with it

        points = qmc.Sobol(2, scramble=True, seed=rng).random(m)
        return points, {"after": rng.bit_generator.state, "points": points.ravel().tolist()}

    return kept("light-samples", "sobol", [scipy.__version__, m, rng.bit_generator.state],
                read, make)


def _frame(axis: NDArray[Any], dtype: Any = np.float64) -> NDArray[Any]:
    """An orthonormal basis (rows t, b, axis) around unit vectors ``axis`` (..., 3),
    branch-free and without cross products (Duff et al. 2017, "Building an Orthonormal
    Basis, Revisited", JCGT 6(1))."""
    a = np.asarray(axis, dtype=dtype)
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    sign = np.where(z >= 0, 1, -1).astype(dtype)
    k = -1 / (sign + z)
    xy = x * y * k
    out = np.empty((*a.shape[:-1], 3, 3), dtype)
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = 1 + sign * x * x * k, sign * xy, -sign * x
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = xy, sign + y * y * k, -y
    out[..., 2, :] = a
    return out


def cone_direction(axis: NDArray[Any], cos_max: NDArray[Any] | float,
                   u: NDArray[Any] | float, v: NDArray[Any] | float,
                   frame: NDArray[Any] | None = None) -> NDArray[np.float64]:
    """Uniform directions in the cone of half-angle acos(cos_max) around ``axis``
    (``frame``: ``_frame(axis)`` if already computed)."""
    cos_t = 1.0 - np.asarray(u) * (1.0 - np.asarray(cos_max))
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2 * math.pi * np.asarray(v)
    f = _frame(axis) if frame is None else frame
    # local (x, y, z) times the frame's rows t, b, axis, written out: einsum is slow here
    return ((sin_t * np.cos(phi))[..., None] * f[..., 0, :]
            + (sin_t * np.sin(phi))[..., None] * f[..., 1, :]
            + np.asarray(cos_t)[..., None] * f[..., 2, :])


def cosine_direction(normal: NDArray[Any] | None, u: NDArray[Any] | float,
                     v: NDArray[Any] | float, frame: NDArray[Any] | None = None
                     ) -> NDArray[np.float64]:
    """Cosine-weighted hemisphere directions around unit ``normal`` (..., 3); u and v are
    scalars or one per point."""
    f = _frame(normal) if frame is None else frame
    uu = np.asarray(u, dtype=f.dtype)[..., None]
    phi = np.asarray(v, dtype=f.dtype)[..., None] * f.dtype.type(2 * math.pi)
    r, z = np.sqrt(uu), np.sqrt(np.maximum(0, 1 - uu))
    return r * np.cos(phi) * f[..., 0, :] + r * np.sin(phi) * f[..., 1, :] + z * f[..., 2, :]


def dome_radiance(light: Light, directions: NDArray[Any],
                  texture: NDArray[np.float32] | None) -> NDArray[np.float64]:
    """A dome light's radiance along world ``directions``: its colour, times a latlong
    texture looked up in the light's frame (+Y up, u = 0.5 at -Z)."""
    if texture is None:
        return np.broadcast_to(light.radiance, directions.shape).astype(np.float64)
    local = directions @ np.linalg.inv(light.matrix[:3, :3])
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    h, w = texture.shape[:2]
    u = 0.5 + np.arctan2(local[:, 0], -local[:, 2]) / (2 * math.pi)
    v = np.arccos(np.clip(local[:, 1], -1, 1)) / math.pi
    x = np.clip((u * w).astype(np.int64), 0, w - 1)
    y = np.clip((v * h).astype(np.int64), 0, h - 1)
    return texture[y, x, :3].astype(np.float64) * light.radiance


# -------------------------------------------------------------------------- irradiance


def emitting_area(light: Light) -> float:
    """The area of a sphere or rect light in scene units^2 (0 for distant and dome)."""
    if light.kind == "sphere":
        return 4 * math.pi * max(light.radius, 1e-9) ** 2
    if light.kind == "rect":
        m = light.matrix
        return abs(light.width * light.height) * float(
            np.linalg.norm(np.cross(m[0, :3], m[1, :3])))
    return 0.0


def surface_radiance(light: Light) -> NDArray[np.float64]:
    """The radiance leaving the light's surface: UsdLux ``normalize`` divides it by the
    light's area, so that power does not change with size."""
    area = emitting_area(light)
    return light.radiance / max(area, 1e-12) if light.normalize and area > 0 else light.radiance


def sphere_cone(light: Light, points: NDArray[Any]
                ) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    """Distance from ``points`` to a sphere light's centre, the unit axis towards it and
    the cosine of the cone the sphere subtends."""
    to_c = light.position - points
    dist = np.linalg.norm(to_c, axis=1)
    axis = to_c / np.maximum(dist, 1e-12)[:, None]
    r = max(light.radius, 1e-9)
    cos_max = np.sqrt(1 - np.clip((r / np.maximum(dist, r * 1.0001)) ** 2, 0, 1))
    return dist, axis, cos_max


def light_direction(light: Light, pos: NDArray[Any]) -> tuple[NDArray[Any], NDArray[Any]]:
    """Unit directions from points to a light's centre, and the irradiance it gives a
    surface facing it (L x solid angle, or L x area x cos / d^2): for the specular lobe
    and for occluders, which see each light from its centre."""
    if light.kind == "distant":
        return (np.broadcast_to(-light.axis, pos.shape),
                np.broadcast_to(light.radiance, pos.shape))
    radiance = surface_radiance(light)
    if light.kind == "sphere":
        _, axis, cos_max = sphere_cone(light, pos)
        return axis, (2 * math.pi * (1 - cos_max))[:, None] * radiance
    to = light.position - pos
    d = np.linalg.norm(to, axis=1, keepdims=True)
    l_dir = to / np.maximum(d, 1e-12)
    cos_l = np.maximum(-(l_dir @ light.axis), 0)[:, None]
    return l_dir, radiance * emitting_area(light) * cos_l / np.maximum(d * d, 1e-12)


_SAMPLE_KERNEL = r"""
// Sample k of every point of a sphere light (KIND 1: uniform in the cone it subtends)
// or an untextured dome (KIND 2: cosine-weighted about the normal), as
// LightSampler.sample does it, with the fraction that enters the skin folded into the
// weight: 1 - rho_dt(cos), linear in the table (specular_albedo). The cone and the
// frame (Duff et al. 2017) are made here per point, not uploaded.
// Eight points per work-item, their arithmetic in float8 (loads and stores lane by
// lane): PoCL's LLVM finds vectorising its work-item loop "not beneficial" for this
// kernel (the strided xyz, the gathered strata and table), and the scalar loop took
// 8.9 ms for the sphere on 481k points, against 2.3-3.0 in vectors, the same values
// bit for bit (each lane's operations are the scalar ones, in the same order; the
// square root is OpenCL's correctly rounded one). Lanes past n repeat the last point
// and are not stored.
// The shadow ray's length comes out too (to the sphere's surface, from the distance
// made here): 0 where the sample carries nothing (the host's np.where for it took 2.2 ms
// a sample at texture 1024, the cast rays' own time 80 ms).
#define LANES(M) M(0) M(1) M(2) M(3) M(4) M(5) M(6) M(7)
__kernel void sample_entering(__global const float *origin, __global const float *normal,
                              __global const float *strata_uv, __global const uchar *classes,
                              __global const int *sets,
                              const float lx, const float ly, const float lz,
                              const float radius, __global const float *table,
                              const int table_n, const int k, __global float *dir,
                              __global float *weight, __global float *ray_far, const int n,
                              const int first)
{
    const int i0 = (int)get_global_id(0) * 8;
    if (i0 >= n) return;
    size_t at[8];  // each lane's point: n of them from `first`, written from 0
#define AT(l) at[l] = (size_t)first + (size_t)(i0 + l < n ? i0 + l : n - 1);
    LANES(AT)
    // (u, cos 2 pi v, sin 2 pi v) of the stratum: the host takes the trigonometry
    float8 u, cv, sv;
#if INTERLEAVED  // the k-th stratum of the point's class (sets: a row of COUNT each)
#define UV(l) { __global const float *uv = strata_uv + \
                    (size_t)4 * sets[(int)classes[at[l]] * COUNT + k]; \
                u.s##l = uv[0]; cv.s##l = uv[1]; sv.s##l = uv[2]; }
    LANES(UV)
#else
    u = strata_uv[4 * k]; cv = strata_uv[4 * k + 1]; sv = strata_uv[4 * k + 2];
#endif
    float8 nx, ny, nz;
#define NORMAL(l) nx.s##l = normal[3 * at[l]]; ny.s##l = normal[3 * at[l] + 1]; \
                  nz.s##l = normal[3 * at[l] + 2];
    LANES(NORMAL)
    float8 ax, ay, az, a, b, c;  // the frame's axis; local coordinates along t, b, axis
#if KIND == 1
    float8 ox, oy, oz;
#define ORIGIN(l) ox.s##l = origin[3 * at[l]]; oy.s##l = origin[3 * at[l] + 1]; \
                  oz.s##l = origin[3 * at[l] + 2];
    LANES(ORIGIN)
    const float8 tx = lx - ox, ty = ly - oy, tz = lz - oz;
    const float8 dist = sqrt(tx * tx + ty * ty + tz * tz);
    const float8 inv = 1.0f / (dist > 1e-12f ? dist : 1e-12f);
    ax = tx * inv; ay = ty * inv; az = tz * inv;
    const float8 q = radius / (dist > 1.0001f * radius ? dist : 1.0001f * radius);
    const float8 cos_max = sqrt(1.0f - q * q);
    const float8 one_minus = q * q / (1.0f + cos_max);  // 1 - cos_max without cancellation
    c = 1.0f - u * one_minus;
    const float8 s2 = 1.0f - c * c;
    const float8 sin_t = sqrt(s2 > 0.0f ? s2 : 0.0f);
    a = sin_t * cv; b = sin_t * sv;
#else
    ax = nx; ay = ny; az = nz;
    const float8 r = sqrt(u);
    c = sqrt(u < 1.0f ? 1.0f - u : 0.0f);
    a = r * cv; b = r * sv;
#endif
    const float8 sgn = az >= 0.0f ? 1.0f : -1.0f;
    const float8 kk = -1.0f / (sgn + az);
    const float8 xy = ax * ay * kk;
    const float8 dx = a * (1.0f + sgn * ax * ax * kk) + b * xy + c * ax;
    const float8 dy = a * sgn * xy + b * (sgn + ay * ay * kk) + c * ay;
    const float8 dz = -a * sgn * ax - b * ay + c * az;
    const float8 cos_n = nx * dx + ny * dy + nz * dz;
    const float8 x = (cos_n > 0.0f ? (cos_n < 1.0f ? cos_n : 1.0f) : 0.0f) *
                     (float)(table_n - 1);
    const int8 xi = convert_int8(x);  // toward zero, as C's cast
    const int8 j = xi < table_n - 2 ? xi : table_n - 2;
    float8 t0, t1;
#define TABLE(l) t0.s##l = table[j.s##l]; t1.s##l = table[j.s##l + 1];
    LANES(TABLE)
    const float8 enters = 1.0f - (t0 + (x - convert_float8(j)) * (t1 - t0));
#if KIND == 1
    const float8 wi = (cos_n > 0.0f ? cos_n : 0.0f) * 6.283185307179586f * one_minus
                      / (float)COUNT * enters;
    const float8 far = wi > 0.0f && dist > radius ? dist - radius : 0.0f;  // ends at it
#else
    const float8 wi = 3.141592653589793f / (float)COUNT * enters;
    const float8 far = wi > 0.0f ? INFINITY : 0.0f;
#endif
#define STORE(l) if (i0 + l < n) { const size_t o = (size_t)(i0 + l); \
        dir[3 * o] = dx.s##l; dir[3 * o + 1] = dy.s##l; dir[3 * o + 2] = dz.s##l; \
        weight[o] = wi.s##l; ray_far[o] = far.s##l; }
    LANES(STORE)
}
"""
SAMPLE_POINTS_PER_ITEM = 8
"""Points one work-item of the light-sample kernel makes (its float8 lanes)."""
DEVICE_SAMPLED_KINDS = ("sphere", "dome")
"""Light kinds sampled on the OpenCL device (a dome only without a texture); the rest in
numpy. Measured on 1.88 M points (the demo face at texture 2048): one sample with its
entering weight 0.26-0.41 s in numpy, 21-23 ms on the device with the download."""


_SAMPLE_LOCK = threading.Lock()


@device_cache(maxsize=8)
def _sample_kernel(kind: str, count: int, interleaved: bool) -> Any:

    # where kernels are compiled at their first launch (PoCL) both kinds share one
    # program: a build's fixed cost (0.29 s cold) once
    kinds = (1, 2) if jit_at_first_launch() else (1 if kind == "sphere" else 2,)
    source = "".join(f"#define KIND {k}\n" + _SAMPLE_KERNEL.replace(
        "sample_entering(", f"sample_entering_{k}(") + "#undef KIND\n" for k in kinds)
    program = build(source, [f"-DCOUNT={count}", f"-DINTERLEAVED={int(interleaved)}"])
    return Kernel(program, f"sample_entering_{1 if kind == 'sphere' else 2}", 1)


class LightSampler:
    """Stratified samples of one light as seen from surface points: ``sample(k)`` gives
    unit directions towards the light, the distance to it (for the shadow ray), and the
    irradiance the sample carries before shadowing and Fresnel: a scalar geometric
    factor per point (cos x solid angle, or cos x cos x area / d^2, over the samples per
    point) and the light's colour, or (N, 3) per point for a textured dome.

    With ``interleave`` (one class 0 to p^2 - 1 per point, from the texel's position
    modulo the ``period`` p), point i traces only the strata ``sets[interleave[i]]``
    (:func:`light_sample_set`): a p^2-th of the rays, the rest borrowed from its
    neighbours by ``filter_interleaved``.
    ``point_buffers`` (a dict, empty at first) lets the samplers of several lights over
    the same points share one device buffer each of the origins, normals and classes.
    ``sequence``: the sample points, :func:`light_sample_set`. With ``complement`` as well,
    each point traces the strata its class does not, the other classes' sets in turn
    (:func:`refine_penumbrae`: with its first share, all of them)."""

    def __init__(self, light: Light, origins: NDArray[Any], normals: NDArray[Any],
                 samples: int, rng: np.random.Generator,
                 dome_texture: NDArray[np.float32] | None = None,
                 interleave: NDArray[Any] | None = None, roughness: float = DEFAULT_ROUGHNESS,
                 rho_s: float = DEFAULT_RHO_S, device: bool = True,
                 point_buffers: dict[str, Any] | None = None,
                 sequence: str = "stratified", complement: bool = False,
                 period: int = 2) -> None:
        self.light = light
        self.roughness, self.rho_s = float(roughness), float(rho_s)
        self.origins = origins
        self.normals = normals
        self.sets: NDArray[np.int32] | None = None
        """Interleaved: the strata each class traces (p^2, count); else None."""
        self.classes: NDArray[np.uint8] | None = None
        # a light of zero extent has one direction: one ray says all, and interleaving
        # it (then filtering) would only blur its hard shadow
        if is_delta_light(light):
            samples = 1
        self.grid, sets = light_sample_set(samples, rng, interleave is not None, sequence,
                                           period)
        if sets is not None and complement:
            sets = complement_sets(sets)
        if sets is not None:
            # a byte per point for its class, not its strata (count int32 per point, 123
            # MB a light at texture 4096, gathered and then copied to the device)
            self.sets = np.ascontiguousarray(sets, np.int32)
            self.classes = (np.asarray(interleave) % (period * period)).astype(
                np.uint8, copy=False)
            self.count = self.sets.shape[1]
        else:
            self.count = self.grid.shape[0]
        self.texture = dome_texture
        # a textured dome's colour varies per direction and is carried by the weights
        self.colour = np.ones(3, np.float32) if light.kind == "dome" and dome_texture is not \
            None else surface_radiance(light).astype(np.float32)
        # the device kernel makes a sphere's cone and every frame per point itself
        on_device = device and light.kind in DEVICE_SAMPLED_KINDS and dome_texture is None
        radius = max(light.radius, 1e-9)
        if light.kind == "distant":
            self.half = math.radians(max(light.angle_deg, 0.0)) / 2
            self.frame = _frame(-light.axis)
        elif light.kind == "sphere":
            if not on_device:  # the device makes the cone and the rays' length per point
                dist, axis, self.cos_max = sphere_cone(light, origins)
                self.solid = 2 * math.pi * (1 - self.cos_max)
                self.frame = _frame(axis, np.float32)
                self.far = np.maximum(dist - radius, 0.0).astype(np.float32)  # rays end at it
        elif light.kind == "rect":
            self.area = emitting_area(light)
        elif light.kind == "dome":
            if not on_device:
                self.frame = _frame(normals, np.float32)
        else:
            raise InputError(f"unsupported light kind {light.kind!r} at {light.path}")
        self._sphere = [np.float32(x) for x in (*np.asarray(light.position)[:3], radius)]
        self.device = self._device_setup({} if point_buffers is None else point_buffers) \
            if on_device else None

    def _device_setup(self, points: dict[str, Any]) -> dict[str, Any]:
        """The device buffers :meth:`entering_sample` reads, uploaded once per sampler;
        the origins and normals once into ``points``, which samplers of the same points
        share."""
        def buf(a: Any, dtype: Any = np.float32) -> Any:
            return device_buffer(np.asarray(a, dtype))

        if "origin" not in points:
            # the arrays themselves on a CPU device (the callers keep them, unchanged,
            # until the samplers close), not copies. With the classes: the two samplers of
            # the demo scene at texture 4096 0.41-0.50 -> 0.17-0.24 s, the irradiance
            # task's peak memory 0.16 GB lower
            points.update(origin=host_buffer(np.asarray(self.origins, np.float32)),
                          normal=host_buffer(np.asarray(self.normals, np.float32)))
        if self.classes is not None and "classes" not in points:
            points["classes"] = host_buffer(self.classes)
        table = _rho_dt_table(self.roughness, self.rho_s)
        u, v = self.grid[:, 0], self.grid[:, 1]
        strata_uv = np.stack([u, np.cos(2 * math.pi * v), np.sin(2 * math.pi * v), 0 * u], 1)
        interleaved = self.sets is not None
        return {**points, "strata_uv": buf(strata_uv),
                "classes": points["classes"] if interleaved else buf([0], np.uint8),
                "sets": buf(self.sets if interleaved else [0], np.int32),
                "table": buf(table), "table_n": np.int32(table.size),
                "kernel": _sample_kernel(self.light.kind, self.count, interleaved)}

    def close(self) -> None:
        """Let the device buffers go (a light's sampler is done once its rays are)."""
        self.device = None

    def entering_sample(self, k: int, rays_into: tuple[NDArray[np.float32], NDArray[np.float32]]
                        | None = None, span: tuple[int, int] | None = None
                        ) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
        """:meth:`sample` with the weight times the fraction entering the skin,
        1 - rho_dt(n . d), and the shadow ray's length 0 where the weight is
        (:meth:`~.raytrace.RayScene.occluded` does not trace it): on the device for
        :data:`DEVICE_SAMPLED_KINDS` (a dome only untextured), else in numpy. Safe to
        call from several threads. ``rays_into``: (N, 3) and (N,) float32 arrays the
        device writes the directions and lengths into (a caller's own from sample to
        sample), else new ones. ``span``: (first, count), the sample of those points only
        (on the device; None: every point)."""
        if self.device is None:
            if span is not None and span != (0, self.origins.shape[0]):
                raise InputError("a span of points is sampled on the device only")
            d, dist, w = self.sample(k)
            enters = 1 - specular_albedo(np.einsum("ij,ij->i", self.normals, d),
                                         self.roughness, self.rho_s)
            w = w * (enters if w.ndim == 1 else enters[:, None])
            return d, np.where((w if w.ndim == 1 else w.max(axis=1)) > 0, dist,
                               np.float32(0)), w
        dev = self.device
        first, n = (0, self.origins.shape[0]) if span is None else span
        d_into, far_into = rays_into if rays_into is not None else (
            np.empty((n, 3), np.float32), np.empty(n, np.float32))
        out = (d_into, np.empty(n, np.float32), far_into)
        if n == 0:  # no launch: mapping an empty output is an OpenCL error
            return out[0], out[2], out[1]
        _, queue = cl_context()
        # each sample's own arrays, written in place on a CPU device (a copy out of
        # device buffers took 1.3-2.9 ms of a sample's 4-7 at texture 1024)
        buffers = [host_output(a) for a in out]
        with _SAMPLE_LOCK:  # a kernel object's arguments are shared: one launch at a time
            dev["kernel"](queue, (-(-n // SAMPLE_POINTS_PER_ITEM),), None, dev["origin"],
                          dev["normal"], dev["strata_uv"], dev["classes"], dev["sets"],
                          *self._sphere, dev["table"], dev["table_n"], np.int32(k), *buffers,
                          np.int32(n), np.int32(first))
        for buffer, array in zip(buffers, out, strict=True):
            read_output(queue, buffer, array)
        d, w, far = out
        return d, far, w

    @cached_property
    def inf(self) -> NDArray[np.float32]:
        """The rays' length toward a light at infinity, per point, for the samples made in
        numpy (:meth:`sample`), made on first use: the device's kernel writes its own
        lengths (a light's 29 MB at texture 4096, held to the end of its rays)."""
        return np.full(self.origins.shape[0], np.inf, np.float32)

    def sample(self, k: int) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
        """Sample k of every point: one stratum for all, or the point's k-th stratum (in
        numpy: a sampler made with ``device=False``, or of a kind the device does not
        sample)."""
        if self.device is not None:
            raise InputError(f"light {self.light.path}: sampled on the device "
                             "(entering_sample); make the sampler with device=False")
        if self.sets is None or self.classes is None:
            u, v = self.grid[k]
        else:
            u, v = self.grid[self.sets[self.classes, k]].T
        light, nrm = self.light, self.normals
        if light.kind == "distant":
            d = cone_direction(-light.axis, math.cos(self.half), u, v, self.frame) \
                if self.half > 0 else -light.axis
            d = d.astype(np.float32)
            if d.ndim == 1:
                w = np.maximum(nrm @ d, 0) / self.count
                return np.broadcast_to(d, nrm.shape), self.inf, w
            return d, self.inf, np.maximum((nrm * d).sum(axis=1), 0) / self.count
        if light.kind == "sphere":
            d = cone_direction(None, self.cos_max, u, v, self.frame).astype(np.float32)
            w = np.maximum((nrm * d).sum(axis=1), 0) * self.solid / self.count
            return d, self.far, w
        if light.kind == "rect":
            zero = np.zeros_like(np.asarray(u, dtype=np.float64))
            local = np.stack([(np.asarray(u) - 0.5) * light.width,
                              (np.asarray(v) - 0.5) * light.height, zero, zero + 1], axis=-1)
            to_p = (local @ light.matrix)[..., :3].astype(np.float32) - self.origins
            dist = np.linalg.norm(to_p, axis=1)
            d = to_p / np.maximum(dist, 1e-12)[:, None]
            cos_s = np.maximum((nrm * d).sum(axis=1), 0)
            cos_l = np.maximum(-(d @ light.axis.astype(np.float32)), 0)
            w = cos_s * cos_l * self.area / np.maximum(dist * dist, 1e-12) / self.count
            return d, dist * np.float32(1 - 1e-4), w
        d = cosine_direction(None, u, v, self.frame).astype(np.float32)
        w = np.full(nrm.shape[0], math.pi / self.count, np.float32)
        if self.texture is not None:
            return d, self.inf, w[:, None] * dome_radiance(light, d, self.texture)
        return d, self.inf, w


_INTERLEAVE_KERNEL = r"""
// one work-item per texel (AT: per texel of the list at, flat indices); planes (light,
// y, x) of the visibility, its sign bit set where the texel traced no ray toward the
// light (-0.0 for 0: visibility_plane): one load a light and tap where a plane of its
// own was two, and the host made that plane as floats (texture 4096, period 4, two
// lights: the kernel 0.53-0.56 -> 0.46 s); normals packed xyz per texel, read as
// floats (vload3, dot and abs are calls or vector values to PoCL, which then does not
// vectorise the work-item loop). The tent spans PERIOD - 1 texels each side, weights
// (PERIOD - |dx|)(PERIOD - |dy|): each class of the period weighs the same.
// A light's sums are scalars of their own (FOR_LIGHTS) and a tap beyond the texture's
// edge or across a crease weighs 0 rather than being skipped: with arrays of LIGHTS
// sums and a branch per tap the kernel kept its sums on the stack, and the 49 taps of
// period 4 at texture 4096 took 1.0-1.2 s against 0.7-1.0; the same values (a tap of
// weight 0 adds +0 to sums of non-negative terms)
#if LIGHTS == 1
#define FOR_LIGHTS(M) M(0)
#elif LIGHTS == 2
#define FOR_LIGHTS(M) M(0) M(1)
#elif LIGHTS == 3
#define FOR_LIGHTS(M) M(0) M(1) M(2)
#else
#define FOR_LIGHTS(M) M(0) M(1) M(2) M(3)
#endif
__kernel void filter_interleaved(__global const float *vis,
                                 __global const float *normal, __global float *out,
                                 const int h, const int w, const float min_cos
#if AT
                                 , __global const int *at, const int n)
{
    const int o = get_global_id(0);
    if (o >= n) return;
    const int i = at[o], x = i % w, y = i / w, stride = n;  // out: (light, n)
#else
                                 )
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const int i = y * w + x, o = i, stride = h * w;  // out: planes like vis
#endif
    const float nx = normal[3 * i], ny = normal[3 * i + 1], nz = normal[3 * i + 2];
    const int plane = h * w;
#define SUMS(l) float num##l = 0.0f, den##l = 0.0f;
    FOR_LIGHTS(SUMS)
    for (int dy = 1 - PERIOD; dy < PERIOD; ++dy) {
        const int yy = y + dy;
        const int y_in = yy >= 0 && yy < h;
        const int row = (y_in ? yy : y) * w;
        const float ty = (float)(PERIOD - (dy < 0 ? -dy : dy));
        for (int dx = 1 - PERIOD; dx < PERIOD; ++dx) {
            const int xx = x + dx;
            const int in = y_in && xx >= 0 && xx < w;
            const int j = row + (in ? xx : x);  // an edge's tap reads the texel, weight 0
            const float cos_n = nx * normal[3 * j] + ny * normal[3 * j + 1] +
                                nz * normal[3 * j + 2];
            const float tent = in && !(cos_n < min_cos) ?
                               ty * (float)(PERIOD - (dx < 0 ? -dx : dx)) : 0.0f;
// an untraced tap weighs 0 (its value is -v: 0 x -v adds -0 to sums of non-negative
// terms, which leaves them as they were)
#define TAP(l) { const float v = vis[l * plane + j]; \
                 const float kt = as_int(v) >= 0 ? tent : 0.0f; \
                 num##l += kt * v; den##l += kt; }
            FOR_LIGHTS(TAP)
        }
    }
// no tap weighed: the texel's own visibility, its sign bit cleared (fabs is a call)
#define OUT(l) out[l * stride + o] = den##l > 0.0f ? num##l / den##l : \
                                     as_float(as_uint(vis[l * plane + i]) & 0x7fffffffu);
    FOR_LIGHTS(OUT)
}
"""
MAX_FILTER_LIGHTS = 4
"""Lights one filter launch handles (a kernel is built per count, loops unrolled); more
go in further launches."""


@device_cache(maxsize=4 * MAX_FILTER_LIGHTS)
def _interleave_kernel(lights: int, at: bool = False, period: int = 2) -> Any:

    program = build(_INTERLEAVE_KERNEL, [f"-DLIGHTS={lights}", f"-DAT={int(at)}",
                                         f"-DPERIOD={period}"])
    return Kernel(program, "filter_interleaved", 1 if at else 2)


_PENUMBRA_KERNEL = r"""
// penumbra_texels at the texels of the list at (flat indices): the maximum and minimum
// of the visibility over traced texels within PERIOD - 1 of the texel (the filter's
// reach), where an untraced texel or one beyond the texture's edge counts 0 for the
// maximum and 1 for the minimum (the numpy definition's constant edges); comparisons
// only, so the same booleans
__kernel void penumbra_at(__global const float *vis, __global const uchar *traced,
                          __global const int *at, const int h, const int w, const int n,
                          __global uchar *out)
{
    const int o = get_global_id(0);
    if (o >= n) return;
    const int i = at[o], x = i % w, y = i / w;
    float hi = -INFINITY, lo = INFINITY;
    for (int dy = 1 - PERIOD; dy < PERIOD; ++dy) {
        for (int dx = 1 - PERIOD; dx < PERIOD; ++dx) {
            const int xx = x + dx, yy = y + dy;
            const int j = yy * w + xx;
            const int in = xx >= 0 && xx < w && yy >= 0 && yy < h && traced[j];
            const float up = in ? vis[j] : 0.0f, down = in ? vis[j] : 1.0f;
            hi = up > hi ? up : hi;
            lo = down < lo ? down : lo;
        }
    }
    const float v = vis[i];
    out[o] = traced[i] && (hi > lo || (v > 0.0f && v < 1.0f));
}
"""


@device_cache(maxsize=len(INTERLEAVE_PERIODS))
def _penumbra_kernel(period: int = 2) -> Any:
    return Kernel(build(_PENUMBRA_KERNEL, [f"-DPERIOD={period}"]), "penumbra_at", 1)


def sample_plan(light: Light, samples: int, interleaved: bool,
                sequence: str = "stratified", period: int = 2) -> tuple[int, bool]:
    """(samples each point traces, whether they are interleaved) for ``light`` at
    ``samples`` per point, as :class:`LightSampler` takes them from
    :func:`light_sample_set`, without making the points (the prewarm's plan asks)."""
    n = 1 if is_delta_light(light) else samples
    classes = period * period
    if sequence == "sobol":
        points = sobol_points(n)
        return (points // classes, True) if interleaved and points >= classes else \
            (points, False)
    if interleaved and n >= classes:
        nx, ny = grid_shape(n, period)
        return nx * ny // classes, True
    nx, ny = grid_shape(n)
    return nx * ny, False


def irradiance_kernels(lights: Sequence[Light], samples: int, interleaved: bool,
                       textured_domes: Collection[str] = (), filtered: bool = True,
                       sequence: str = "stratified", refined: bool = False,
                       period: int = 2) -> list[Any]:
    """The device kernels :func:`irradiance_texture` and (if ``filtered``)
    :func:`filter_interleaved` at the covered texels (``at``, as the renderer runs it)
    or (if ``refined``) :func:`refine_penumbrae`'s :func:`penumbra_at` will launch for
    these lights at the interleaving ``period`` (for :class:`~.opencl.Prewarm`)."""
    kernels, interleaved_lights = [_offset_kernel()], 0
    for light in lights:
        if not np.any(light.radiance > 0):
            continue
        count, inter = sample_plan(light, samples, interleaved, sequence, period)
        interleaved_lights += inter
        if light.kind in DEVICE_SAMPLED_KINDS and light.path not in textured_domes:
            kernels.append(_sample_kernel(light.kind, count, inter))
            if refined and inter:  # the penumbrae's other classes' strata
                kernels.append(_sample_kernel(light.kind, (period * period - 1) * count,
                                              inter))
    if filtered:
        for start in range(0, interleaved_lights, MAX_FILTER_LIGHTS):
            kernels.append(_interleave_kernel(min(MAX_FILTER_LIGHTS,
                                                  interleaved_lights - start), True,
                                              period))
    if refined and interleaved_lights:
        kernels.append(_penumbra_kernel(period))
    return kernels


def flat_texels(at: NDArray[Any], h: int, w: int) -> NDArray[np.int32]:
    """``at`` as the int32 flat indices of texels of an (h, w) texture the device
    kernels read (a 1-D list, each below h w), or InputError."""
    points = np.asarray(at)
    if points.ndim != 1 or (points.size and (points.min() < 0 or points.max() >= h * w)):
        raise InputError(f"at: flat texel indices below {h * w} expected")
    return points.astype(np.int32, copy=False)


def light_planes(visibility: NDArray[Any], carries: NDArray[np.bool_], texel: NDArray[Any],
                 vis_plane: NDArray[np.float32], traced_plane: NDArray[np.bool_]) -> None:
    """One light's visibility per point and whether its rays could carry any light
    (``carries``: :meth:`IrradianceResult.carries_light`) put into (H, W) planes at the
    points' flat texel indices ``texel`` (by flat index: a boolean mask's scatter took
    2-4x as long at texture 4096)."""
    np.put(vis_plane, texel, visibility)
    np.put(traced_plane, texel, carries)


def visibility_planes(lights: int, shape: tuple[int, int]) -> NDArray[np.float32]:
    """(lights, H, W) planes for :func:`visibility_plane`, every texel untraced (-0.0)."""
    return np.full((lights, *shape), -0.0, np.float32)


def visibility_plane(visibility: NDArray[Any], carries: NDArray[np.bool_],
                     texel: NDArray[Any], plane: NDArray[np.float32]) -> None:
    """One light's visibility per point (>= 0) put into its (H, W) ``plane`` (of
    :func:`visibility_planes`) at the points' flat texel indices ``texel``, as
    :func:`filter_interleaved` reads it without ``traced``: negated (its sign bit set,
    -0.0 for 0) where the point's rays could carry no light (``carries`` false:
    :meth:`IrradianceResult.carries_light`)."""
    np.put(plane, texel, np.where(carries, visibility, np.negative(visibility)))


def filter_interleaved(visibility: NDArray[Any], traced: NDArray[Any] | None,
                       normal: NDArray[Any], min_cos: float = 0.9,
                       at: NDArray[Any] | None = None, period: int = 2
                       ) -> NDArray[np.float32]:
    """Texture-space reconstruction of interleaved shadow rays: each texel's visibility
    (L, H, W: one plane per light) becomes the tent average over the (2p - 1)^2 texels
    around it for the ``period`` p, weights (p - |dx|)(p - |dy|) / p^4 ((1 2 1)^2 / 16
    over 3 x 3 at period 2), which weight the p^2 interleaved stratum sets equally
    (Keller & Heidrich 2001). Neighbours count only where ``traced`` > 0 (the texel
    traced rays towards that light) and their normal (H, W, 3) is within acos(min_cos)
    of the texel's, so that a crease or a chart that happens to touch does not bleed.
    OpenCL, one work-item per texel; with ``at`` (flat texel indices, N), only at those
    texels, returned as (L, N) (the renderer's covered texels: the demo face covers 46%
    of its texture). The visibility is a fraction (>= 0); with ``traced`` None, its
    planes say it themselves, negated where a texel traced nothing
    (:func:`visibility_plane`)."""
    vis = np.asarray(visibility, dtype=np.float32)
    if vis.ndim != 3 or (traced is not None and np.shape(traced) != vis.shape) or \
            np.shape(normal) != (*vis.shape[1:], 3):
        raise InputError(f"visibility (L, H, W), traced (L, H, W) and normal (H, W, 3) must "
                         f"agree; got {vis.shape}, {np.shape(traced)}, {np.shape(normal)}")
    if traced is not None:
        if not (vis >= 0).all():
            raise InputError("visibility must be a fraction >= 0 where traced is given; "
                             f"got {float(np.nanmin(vis))}")
        vis = np.where(np.asarray(traced) > 0, vis, np.negative(vis))
    vis = np.ascontiguousarray(vis)
    lights, h, w = vis.shape
    points = None if at is None else flat_texels(at, h, w)
    if points is not None and not points.size:
        return np.zeros((lights, 0), np.float32)
    _, queue = cl_context()
    # over the arrays' own memory on a CPU device (copies of 0.3 GB took 0.5 s at
    # texture 4096)
    nrm_buf = host_buffer(np.asarray(normal, np.float32))
    out = np.empty_like(vis) if points is None else np.empty((lights, points.size),
                                                             np.float32)
    at_args = () if points is None else (host_buffer(points), np.int32(points.size))
    for start in range(0, lights, MAX_FILTER_LIGHTS):
        part = slice(start, min(start + MAX_FILTER_LIGHTS, lights))
        out_part = out[part]
        # the buffers (and the arrays they hold) stay referenced until the read
        vis_buf = host_buffer(vis[part])
        out_buf = host_output(out_part)
        grid = (w, h) if points is None else (points.size,)
        _interleave_kernel(part.stop - start, points is not None, period)(
            queue, grid, None, vis_buf, nrm_buf, out_buf, np.int32(h),
            np.int32(w), np.float32(min_cos), *at_args)
        read_output(queue, out_buf, out_part)
    return out


@dataclass
class IrradianceResult:
    """Irradiance entering the skin per point (``entering``, (N, 3)), and per light the
    fraction of its unshadowed irradiance that arrived (``visibility``, for the specular
    term) and the unshadowed irradiance itself, as weights and a colour, so that
    interleaved visibility can be filtered and applied afterwards (``entering_with``)."""

    arrived: list[tuple[NDArray[np.float32], NDArray[np.float32]]]
    """Per light that adds light, in the lights' order: the weights that reached it per
    point ((N,), or (N, 3) for a textured dome) and its colour (3,): what ``entering``
    sums."""
    visibility: dict[str, NDArray[np.float32]]
    unshadowed: dict[str, tuple[NDArray[np.float32], NDArray[np.float32]]] = \
        field(default_factory=dict)
    """Per light: all its samples' weights per point ((N,), or (N, 3) for a textured
    dome) and its colour (3,), whose product (:func:`coloured`) is its unshadowed
    irradiance (N, 3). Kept apart: the products were 184 MB of new pages and 0.3-0.8 s
    of the main thread beside the rays at texture 4096, and every reader takes a column
    or a test from them."""
    skipped: list[str] = field(default_factory=list)
    rays: int = 0
    seconds: float = 0.0
    interleaved: frozenset[str] = frozenset()
    """Lights whose shadow rays were interleaved (each point traced a share of the
    samples): only their visibility is reconstructed by ``filter_interleaved``."""

    points: int = 0

    @cached_property
    def entering(self) -> NDArray[np.float32]:
        """Irradiance entering the skin per point (N, 3): each light's weights that
        reached it times its colour, summed light by light. Made when first read: an
        interleaved or adaptive render replaces it (``entering_with``), and these sums
        were 1.3 s of its main thread at texture 4096, beside the rays."""
        out = np.zeros((self.points, 3), np.float32)
        for lit, colour in self.arrived:
            if lit.ndim == 1:  # a column at a time, no (N, 3) of products
                for c in range(3):
                    out[:, c] += lit * colour[c]
            else:
                out += lit * colour
        return out

    def entering_with(self, visibility: dict[str, NDArray[Any]]) -> NDArray[np.float32]:
        """Irradiance entering the skin with each light's visibility replaced (e.g. by its
        filtered form): sum of unshadowed x visibility, each unshadowed column made as
        :func:`coloured` makes it (the same products)."""
        out = np.zeros((self.points, 3), np.float32)
        lights = [(weights, colour, np.asarray(visibility[path], np.float32))
                  for path, (weights, colour) in self.unshadowed.items()]

        def band(points: slice) -> None:  # in bands on the cores (0.2 s on one at 4096)
            column = None  # one column's products at a time, reused
            for weights, colour, vis in lights:
                for c in range(3):
                    w = weights[points] if weights.ndim == 1 else weights[points, c]
                    column = np.multiply(w, colour[c], out=column)
                    column *= vis[points]
                    out[points, c] += column

        in_bands(band, self.points)
        return out

    def unshadowed_irradiance(self, path: str) -> NDArray[np.float32]:
        """Light ``path``'s unshadowed irradiance per point (N, 3)."""
        return coloured(*self.unshadowed[path])

    def carries_light(self, path: str) -> NDArray[np.bool_]:
        """Whether light ``path``'s rays could carry any light to each point: its
        unshadowed irradiance summed over the channels > 0. From (N,) weights, without the
        products: ``weights x max(colour) > 0`` is the same test, as the colour is >= 0
        and rounding is monotone (some channel's product is > 0 exactly when the
        largest one is)."""
        weights, colour = self.unshadowed[path]
        if weights.ndim == 1:
            return weights * np.max(colour) > 0
        return sum_axis1(coloured(weights, colour)) > 0


_OFFSET_KERNEL = r"""
// offset_ray_origin per coordinate (points and normals as 3N floats): the integer
// offset away from zero, or p + s n within OFFSET_ORIGIN of zero, rounded as numpy
// rounds it (a product and a sum, not one fused operation)
#pragma OPENCL FP_CONTRACT OFF
__kernel void offset_origin(__global const float *p, __global const float *nrm,
                            const float int_scale, const float near, const float origin,
                            const int n, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const float pc = p[i], nc = nrm[i];
    const int of_i = (int)(int_scale * nc);  // toward zero, as numpy's astype
    const uint shifted = (uint)as_int(pc) + (uint)(pc < 0.0f ? -of_i : of_i);
    out[i] = (pc < 0.0f ? -pc : pc) < origin ? pc + near * nc : as_float(shifted);
}
"""


@device_cache(maxsize=1)
def _offset_kernel() -> Any:
    return Kernel(build(_OFFSET_KERNEL), "offset_origin", 1)


def ray_origins(points: NDArray[Any], normals: NDArray[Any]) -> NDArray[np.float32]:
    """:func:`~.raytrace.offset_ray_origin` on the OpenCL device, the same floats bit for
    bit: the shadow rays' origins (N, 3). numpy's passes took 13 ms of the demo face's
    interleaved irradiance at texture 1024 (0.43 s), before its first ray."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.ascontiguousarray(normals, dtype=np.float32)
    if n.shape != p.shape or p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points and normals must agree as (N, 3); got {p.shape} and "
                         f"{n.shape}")
    out = np.empty_like(p)
    if p.size:
        _, queue = cl_context()
        run_on_host_arrays(_offset_kernel(), queue, (p.size,),
                           [p, n, np.float32(OFFSET_INT_SCALE), np.float32(OFFSET_FLOAT_SCALE),
                            np.float32(OFFSET_ORIGIN), np.int32(p.size)], [out])
    return out


def light_rng(seed: int, light: Light) -> np.random.Generator:
    """The random numbers of one light's samples: the same for the light in every call
    (its samples' grid), whatever other lights are sampled with it."""
    return np.random.default_rng([seed, zlib.crc32(light.path.encode())])


def is_delta_light(light: Light) -> bool:
    """A light of zero extent: a distant light of angle 0 or a sphere of radius 0."""
    return (light.kind == "distant" and light.angle_deg <= 0.0) or \
        (light.kind == "sphere" and light.radius <= 0.0)


def irradiance_texture(
    positions: NDArray[Any], normals: NDArray[Any], lights: list[Light], rays: RayScene,
    samples: int = 16, roughness: float = DEFAULT_ROUGHNESS, rho_s: float = DEFAULT_RHO_S,
    seed: int = 0, dome_textures: dict[str, NDArray[np.float32]] | None = None,
    interleave: NDArray[Any] | None = None, sequence: str = "stratified",
    coherent: bool = False, complement: bool = False, period: int = 2,
) -> IrradianceResult:
    """Irradiance entering the skin at surface points (N, 3) with unit normals, summed
    over ``lights`` with ``samples`` shadow rays per light and point (the points of
    :func:`light_sample_set` for ``sequence``; with ``interleave``, a class 0 to p^2 - 1
    per point for the ``period`` p: a p^2-th of them, see ``LightSampler``; the
    per-point visibility is then noisy until ``filter_interleaved`` has run; with
    ``complement`` too, the other classes' strata).

    Ray origins are pushed off the surface along the normal by what their floating-point
    error needs (:func:`~.raytrace.offset_ray_origin`); rays whose cosine is <= 0 are
    not cast. The rays go to Embree sorted along a Morton curve of their origins, or in
    the points' own order if they are ``coherent`` (neighbours on the surface next to
    each other, as a texture's texels in :func:`~.texture_maps.texels_in_blocks`). Each
    point's result does not depend on the order.
    """
    start = time.perf_counter()
    pos = np.asarray(positions, dtype=np.float32)
    nrm = np.asarray(normals, dtype=np.float32)
    classes = None if interleave is None else np.asarray(interleave)
    back_order = None
    if not coherent:
        order = morton_order(pos)
        # rows gathered by np.take (fancy indexing of (N, 3) rows took 5x as long: 19
        # ms against 4 at texture 1024), and back by the inverse order's take, not a
        # scatter
        pos, nrm = np.take(pos, order, axis=0), np.take(nrm, order, axis=0)
        back_order = np.empty_like(order)
        back_order[order] = np.arange(order.size)
        classes = None if classes is None else classes[order]

    def back(a: NDArray[Any]) -> NDArray[Any]:
        """``a`` (per sorted point) in the points' own order."""
        return a if back_order is None else np.take(a, back_order, axis=0)

    origins = ray_origins(pos, nrm)
    n = pos.shape[0]
    arrived: list[tuple[NDArray[np.float32], NDArray[np.float32]]] = []
    visibility: dict[str, NDArray[np.float32]] = {}
    unshadowed_by_light: dict[str, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
    skipped: list[str] = []
    interleaved: set[str] = set()
    point_buffers: dict[str, Any] = {}  # origins and normals on the device, for every light
    samplers: list[LightSampler] = []
    for light in lights:
        if not np.any(light.radiance > 0):
            skipped.append(f"light {light.path}: zero radiance")
            continue
        samplers.append(LightSampler(light, origins, nrm, samples, light_rng(seed, light),
                                     (dome_textures or {}).get(light.path), classes,
                                     roughness, rho_s, point_buffers=point_buffers,
                                     sequence=sequence, complement=complement,
                                     period=period))
    n_rays = 0
    for sampler, lit, unshadowed, cast in cast_samples(samplers, rays):
        light = sampler.light
        n_rays += cast
        if not unshadowed.any():
            skipped.append(f"light {light.path}: adds nothing (all samples below the "
                           "horizon)")
            continue
        if not lit.any():  # its visibility, 0, is still the specular lobe's and the
            # adaptive pass's (which refines a light's penumbrae from it)
            skipped.append(f"light {light.path}: adds nothing (shadowed everywhere)")
        if sampler.sets is not None:
            interleaved.add(light.path)
        arrived.append((back(lit), sampler.colour))
        visibility[light.path] = back(light_visibility(lit, unshadowed))
        unshadowed_by_light[light.path] = (back(unshadowed), sampler.colour)
    return IrradianceResult(arrived, visibility, unshadowed_by_light, skipped, n_rays,
                            time.perf_counter() - start, frozenset(interleaved), n)


RAY_BLOCK_POINTS = 1 << 21
"""Points whose shadow rays of one sample go to Embree as one job of
:func:`cast_samples` (a sampler on the device; a numpy one's samples go whole): each
worker's rays (16 bytes a point) were a whole sample's, 0.25 GB between the two at
texture 4096, at the irradiance's peak."""


def ray_blocks(sampler: LightSampler) -> list[tuple[int, int]]:
    """(first point, count) of each job of one sample of ``sampler``
    (:data:`RAY_BLOCK_POINTS` at a time on the device; every point at once in numpy)."""
    n = sampler.origins.shape[0]
    if sampler.device is None or n <= RAY_BLOCK_POINTS:
        return [(0, n)]
    return [(s, min(RAY_BLOCK_POINTS, n - s)) for s in range(0, n, RAY_BLOCK_POINTS)]


def cast_samples(samplers: Sequence[LightSampler], rays: RayScene
                 ) -> Iterator[tuple[LightSampler, NDArray[Any], NDArray[Any], int]]:
    """Every sample of every sampler (each over its own points), its shadow rays cast:
    yields per sampler, in turn, (sampler, lit, unshadowed, rays cast), the sums over its
    samples of the weights (entering the skin) that reached the light and of all of
    them, (N,) or (N, 3) for a textured dome. One queue of every sampler's samples on two
    workers: sample k+1's directions are made while sample k's rays are in Embree, and a
    sampler's sums are made (by the caller too) while the next one's rays are: the gaps
    between lights were a tenth of the demo face's interleaved pass at texture 1024,
    and the adaptive pass's lights, one call each, left 60 ms of its 1.1 s idle."""
    worker = threading.local()
    spans = {id(s): ray_blocks(s) for s in samplers}
    most = max((count for s in samplers for _, count in spans[id(s)]), default=0)

    def one(job: tuple[LightSampler, int, tuple[int, int]]) -> tuple[Any, Any, int]:
        # light the specular lobe reflects does not enter the skin; rays of points
        # the sample does not light end where they start (length 0) and are not
        # traced, where gathering the others and scattering their answers back took
        # 25 ms a sample at texture 1024
        sampler, k, (first, n) = job
        if not hasattr(worker, "rays"):
            # each worker's rays from sample to sample in the same arrays (their first
            # rows for fewer points): fresh ones were 0.12 GB of new pages a sample at
            # texture 4096 (zeroed by the kernel)
            worker.rays = (np.empty((most, 3), np.float32), np.empty(most, np.float32))
        d, dist, w = sampler.entering_sample(k, (worker.rays[0][:n], worker.rays[1][:n]),
                                             (first, n))
        cast = int(np.count_nonzero((w if w.ndim == 1 else w.max(axis=1)) > 0))
        if cast == 0:
            return None, None, 0
        open_ = ~rays.occluded(sampler.origins[first:first + n], d, dist)
        # a product, not np.where (2.5 ms a sample on a random mask, 0.3 ms): the
        # weights are finite
        return w * (open_ if w.ndim == 1 else open_[:, None]), w, cast

    jobs = [(sampler, k, span) for sampler in samplers for k in range(sampler.count)
            for span in spans[id(sampler)]]
    pool = ThreadPoolExecutor(2)
    try:
        results = pool.map(one, jobs)
        for i, sampler in enumerate(samplers):
            n = sampler.origins.shape[0]
            lit = np.zeros((n, 3) if sampler.texture is not None else n, np.float32)
            unshadowed = np.zeros_like(lit)
            n_rays = 0
            for first, count in spans[id(sampler)] * sampler.count:  # as the jobs go
                got, full, cast = next(results)
                if got is not None:
                    lit[first:first + count] += got
                    unshadowed[first:first + count] += full
                    n_rays += cast
            sampler.close()
            if i == len(samplers) - 1:
                # the workers end, and their rays' arrays go with them, before the
                # caller's sums of the last light (0.25 GB at texture 4096)
                pool.shutdown(wait=True)
            yield sampler, lit, unshadowed, n_rays
    finally:
        pool.shutdown(wait=True)


def light_visibility(lit: NDArray[Any], unshadowed: NDArray[Any]) -> NDArray[np.float32]:
    """A light's visibility per point from :func:`cast_samples`' sums: the fraction of
    the unshadowed weight that reached it, 0 where none could."""
    lit_s = lit if lit.ndim == 1 else sum_axis1(lit)
    un_s = unshadowed if unshadowed.ndim == 1 else sum_axis1(unshadowed)
    vis = np.where(un_s > 0, lit_s / np.maximum(un_s, 1e-30), 0.0)
    return vis.astype(np.float32, copy=False)


def coloured(weights: NDArray[Any], colour: NDArray[Any]) -> NDArray[np.float32]:
    """A light's unshadowed irradiance (N, 3): its weights ((N,), or (N, 3) for a
    textured dome) times its colour (3,)."""
    return times_colour(weights, colour) if weights.ndim == 1 else weights * colour


def times_colour(values: NDArray[Any], colour: NDArray[Any]) -> NDArray[Any]:
    """``values[:, None] * colour`` (N,) x (3,) -> (N, 3), one column at a time: the same
    products, where numpy's broadcast of (N, 1) against (3,) took 5-6 ms on the demo
    face's 481k texels at texture 1024 (per light, twice, at the end of the irradiance's
    rays) and the columns 0.5 ms."""
    out = np.empty((values.shape[0], 3), np.result_type(values, colour))
    for c in range(3):
        np.multiply(values, colour[c], out=out[:, c])
    return out


def sum_axis1(a: NDArray[Any]) -> NDArray[Any]:
    """``a.sum(axis=1)`` over a short axis 1, its entries added in turn: the same sums
    in the same order, where numpy's reduction over the short axis took 3-6x as long
    (12 against 2-4 ms on the 481k rows of three of the demo face at texture 1024)."""
    out = a[:, 0].copy()
    for k in range(1, a.shape[1]):
        out += a[:, k]
    return out


def penumbra_texels(visibility: NDArray[Any], traced: NDArray[Any],
                    period: int = 2) -> NDArray[np.bool_]:
    """Texels (H, W) whose interleaved shadow rays do not all agree: the texel's own rays
    (visibility strictly between 0 and 1) or those of a traced texel in the (2p - 1)^2
    neighbourhood :func:`filter_interleaved` reads for the ``period`` p (3 x 3 at 2; a
    different visibility). Elsewhere the neighbourhood's rays, all p^2 interleaved sets
    of strata, saw the light all visible or all blocked. The numpy reference of
    :func:`penumbra_at`, which the adaptive pass runs."""
    from scipy.ndimage import maximum_filter, minimum_filter  # lazy, as the fit's solvers

    vis = np.asarray(visibility, np.float32)
    size = 2 * period - 1
    hi = maximum_filter(np.where(traced, vis, 0.0), size=size, mode="constant", cval=0.0)
    lo = minimum_filter(np.where(traced, vis, 1.0), size=size, mode="constant", cval=1.0)
    return traced & ((hi > lo) | ((vis > 0) & (vis < 1)))


def penumbra_at(visibility: NDArray[Any], traced: NDArray[Any],
                at: NDArray[Any], period: int = 2) -> NDArray[np.bool_]:
    """:func:`penumbra_texels` at the texels of ``at`` (flat indices into the (H, W)
    planes), on the OpenCL device: one work-item per listed texel, not two 3 x 3
    filters over the whole texture and a gather (54 ms for the demo face's two lights
    at texture 1024, 46% of whose texels are covered)."""
    vis = np.ascontiguousarray(visibility, np.float32)
    if vis.ndim != 2 or np.shape(traced) != vis.shape:
        raise InputError(f"visibility and traced must be (H, W) planes of one shape; got "
                         f"{vis.shape} and {np.shape(traced)}")
    h, w = vis.shape
    points = flat_texels(at, h, w)
    out = np.zeros(points.size, np.uint8)
    if points.size:
        _, queue = cl_context()
        run_on_host_arrays(_penumbra_kernel(period), queue, (points.size,),
                           [vis, np.ascontiguousarray(traced, np.bool_).view(np.uint8),
                            points, np.int32(h), np.int32(w), np.int32(points.size)], [out])
    return out.view(np.bool_)


def refine_penumbrae(
    result: IrradianceResult, covered: NDArray[np.bool_], positions: NDArray[Any],
    normals: NDArray[Any], interleave: NDArray[Any], lights: list[Light], rays: RayScene,
    samples: int, roughness: float = DEFAULT_ROUGHNESS, rho_s: float = DEFAULT_RHO_S,
    seed: int = 0, dome_textures: dict[str, NDArray[np.float32]] | None = None,
    sequence: str = "stratified", texel: NDArray[np.intp] | None = None,
    coherent: bool = False, period: int = 2,
) -> tuple[IrradianceResult, dict[str, NDArray[np.int64]]]:
    """Adaptive shadow rays: after an interleaved pass of ``period`` p (``result``: every
    covered texel of ``covered`` traced the p^2-th of the strata its ``interleave``
    class names; the points are the texels at flat indices ``texel``, by default in row
    order), the texels of :func:`penumbra_texels` trace the other classes' strata (the
    same strata: :func:`light_rng`), so that their visibility is their own estimate from
    all ``samples``. Every other texel's neighbourhood agreed, so the interleaved
    reconstruction there is its own value: nothing is filtered. The error target is
    full sampling's (each texel's visibility from all ``samples`` strata) at a fraction
    of its rays (cast as :func:`irradiance_texture` casts them, ``coherent`` or not).
    Returns the result (visibility final, ``interleaved`` empty) and the refined points
    (indices into ``positions``) per light."""
    start = time.perf_counter()
    visibility = dict(result.visibility)
    unshadowed = dict(result.unshadowed)
    refined: dict[str, NDArray[np.int64]] = {}
    n_rays = result.rays
    classes = np.asarray(interleave)
    pos = np.asarray(positions, dtype=np.float32)
    nrm = np.asarray(normals, dtype=np.float32)
    if texel is None:
        texel = np.flatnonzero(covered)
    texel32 = flat_texels(texel, *covered.shape)  # once for every light's penumbra
    # every light's penumbra first, then all their rays in one queue (cast_samples):
    # one light's sums are merged while the next one's rays are cast
    samplers: list[LightSampler] = []
    cast_at: dict[str, NDArray[np.int64]] = {}
    for light in lights:
        path = light.path
        if path not in result.interleaved:
            continue
        vis1, traced = np.zeros(covered.shape, np.float32), np.zeros(covered.shape, bool)
        light_planes(result.visibility[path], result.carries_light(path), texel32, vis1,
                     traced)
        where = refined[path] = np.flatnonzero(penumbra_at(vis1, traced, texel32, period))
        if not where.size:
            continue
        # each point's result does not depend on the order: the rays go along a
        # Morton curve of the points unless they are coherent already
        at = cast_at[path] = where if coherent else where[morton_order(pos[where])]
        nrm_at = np.take(nrm, at, axis=0)  # fancy indexing of (N, 3) rows took 5x as long
        # each penumbra texel the strata of the interleaved classes it has not traced
        # (the other p^2 - 1 shares of them, once each)
        samplers.append(LightSampler(light, ray_origins(np.take(pos, at, axis=0), nrm_at),
                                     nrm_at, samples, light_rng(seed, light),
                                     (dome_textures or {}).get(light.path), classes[at],
                                     roughness, rho_s, sequence=sequence, complement=True,
                                     period=period))
    # each pass's weights average over its own strata, 1 / p^2 and the rest of them:
    # the texel's estimate from all of them weights the passes so (0.25 and 0.75 at 2)
    first = np.float32(1.0 / (period * period))
    rest = np.float32(1.0) - first
    for sampler, lit, more_un, cast in cast_samples(samplers, rays):
        path, at = sampler.light.path, cast_at[sampler.light.path]
        n_rays += cast
        vis2 = light_visibility(lit, more_un)
        # weights, not irradiance: the light's colour is in both passes' and cancels in
        # the visibility
        w1, colour = result.unshadowed[path]
        w1_at = np.take(w1, at, axis=0)
        w1_sum = w1_at if w1_at.ndim == 1 else sum_axis1(w1_at)
        w2_sum = more_un if more_un.ndim == 1 else sum_axis1(more_un)
        lit_all = first * result.visibility[path][at] * w1_sum + rest * vis2 * w2_sum
        w_sum = first * w1_sum + rest * w2_sum
        vis = visibility[path] = visibility[path].copy()
        vis[at] = np.where(w_sum > 0, lit_all / np.maximum(w_sum, 1e-30), 0.0)
        w = w1.copy()
        w[at] = first * w1_at + rest * more_un
        unshadowed[path] = (w, colour)
    out = replace(result, visibility=visibility, unshadowed=unshadowed, rays=n_rays,
                  seconds=result.seconds + time.perf_counter() - start,
                  interleaved=frozenset())
    out.entering = out.entering_with(visibility)
    return out, refined

