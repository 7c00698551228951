"""Where a light is sampled from a texel: scrambled Sobol or jittered-grid points on its
surface or solid angle, the interleaved sets each texel class traces, and the device
kernel that turns them into shadow-ray directions and radiance."""

from __future__ import annotations

import math
import threading
import zlib
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..cache import kept
from ..device.choice import Device
from ..device.memory import (
    device_buffer,
    host_buffer,
    host_output,
    read_output,
)
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from ..options import INTERLEAVE_PERIODS
from ..scene import Light
from .boundary import transmission_lookup, transmission_table

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
    scipy.stats for them takes 0.6-0.9 s of CPU with the GIL held, which slowed the
    texture maps beside it by half again. A kept file that does not read back is made
    again; one that cannot be written is not kept."""
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


def orthonormal_frame(axis: NDArray[Any], dtype: Any = np.float64) -> NDArray[Any]:
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
    (``frame``: ``orthonormal_frame(axis)`` if already computed)."""
    cos_t = 1.0 - np.asarray(u) * (1.0 - np.asarray(cos_max))
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2 * math.pi * np.asarray(v)
    f = orthonormal_frame(axis) if frame is None else frame
    # local (x, y, z) times the frame's rows t, b, axis, written out: einsum is slow here
    return ((sin_t * np.cos(phi))[..., None] * f[..., 0, :]
            + (sin_t * np.sin(phi))[..., None] * f[..., 1, :]
            + np.asarray(cos_t)[..., None] * f[..., 2, :])


def cosine_direction(normal: NDArray[Any] | None, u: NDArray[Any] | float,
                     v: NDArray[Any] | float, frame: NDArray[Any] | None = None
                     ) -> NDArray[np.float64]:
    """Cosine-weighted hemisphere directions around unit ``normal`` (..., 3); u and v are
    scalars or one per point."""
    f = orthonormal_frame(normal) if frame is None else frame
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


_SAMPLE_KERNEL = cl_source(__package__, "light_samples.cl")
SAMPLE_POINTS_PER_ITEM = 8
"""Points one work-item of the light-sample kernel makes (its float8 lanes)."""
DEVICE_SAMPLED_KINDS = ("sphere", "dome")
"""Light kinds sampled on the OpenCL device (a dome only without a texture); the rest in
numpy. Measured on 1.88 M points (the demo face at texture 2048): one sample with its
entering weight 0.26-0.41 s in numpy, 21-23 ms on the device with the download."""


_SAMPLE_LOCK = threading.Lock()


@lru_cache(maxsize=8)
def _sample_kernel(device: Device, kind: str, count: int, interleaved: bool) -> Any:
    # where kernels are compiled at their first launch (PoCL) both kinds share one
    # program: a build's fixed cost (0.29 s cold) once
    kinds = (1, 2) if device.jit_at_first_launch else (1 if kind == "sphere" else 2,)
    source = "".join(f"#define KIND {k}\n" + _SAMPLE_KERNEL.replace(
        "sample_entering(", f"sample_entering_{k}(") + "#undef KIND\n" for k in kinds)
    program = build(device, source, [f"-DCOUNT={count}", f"-DINTERLEAVED={int(interleaved)}"])
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
    (:func:`refine_penumbrae`: with its first share, all of them). ``device``: where
    the samples of :data:`DEVICE_SAMPLED_KINDS` are made (None: in numpy)."""

    def __init__(self, light: Light, origins: NDArray[Any], normals: NDArray[Any],
                 samples: int, rng: np.random.Generator,
                 dome_texture: NDArray[np.float32] | None = None,
                 interleave: NDArray[Any] | None = None, eta: float = 1.0,
                 device: Device | None = None,
                 point_buffers: dict[str, Any] | None = None,
                 sequence: str = "stratified", complement: bool = False,
                 period: int = 2) -> None:
        self.light = light
        self.eta = float(eta)
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
        on_device = device is not None and light.kind in DEVICE_SAMPLED_KINDS and \
            dome_texture is None
        radius = max(light.radius, 1e-9)
        if light.kind == "distant":
            self.half = math.radians(max(light.angle_deg, 0.0)) / 2
            self.frame = orthonormal_frame(-light.axis)
        elif light.kind == "sphere":
            if not on_device:  # the device makes the cone and the rays' length per point
                dist, axis, self.cos_max = sphere_cone(light, origins)
                self.solid = 2 * math.pi * (1 - self.cos_max)
                self.frame = orthonormal_frame(axis, np.float32)
                self.far = np.maximum(dist - radius, 0.0).astype(np.float32)  # rays end at it
        elif light.kind == "rect":
            self.area = emitting_area(light)
        elif light.kind == "dome":
            if not on_device:
                self.frame = orthonormal_frame(normals, np.float32)
        else:
            raise InputError(f"unsupported light kind {light.kind!r} at {light.path}")
        self._sphere = [np.float32(x) for x in (*np.asarray(light.position)[:3], radius)]
        self.device = self._device_setup(device, {} if point_buffers is None else
                                         point_buffers) if on_device else None

    def _device_setup(self, device: Any, points: dict[str, Any]) -> dict[str, Any]:
        """The device buffers :meth:`entering_sample` reads, uploaded once per sampler;
        the origins and normals once into ``points``, which samplers of the same points
        share."""
        def buf(a: Any, dtype: Any = np.float32) -> Any:
            return device_buffer(device, np.asarray(a, dtype))

        if "origin" not in points:
            # the arrays themselves on a CPU device (the callers keep them, unchanged,
            # until the samplers close), not copies: half the samplers' time and 0.16 GB
            # of the irradiance task's peak at texture 4096
            points.update(origin=host_buffer(device, np.asarray(self.origins, np.float32)),
                          normal=host_buffer(device, np.asarray(self.normals, np.float32)))
        if self.classes is not None and "classes" not in points:
            points["classes"] = host_buffer(device, self.classes)
        table = transmission_table(self.eta)
        u, v = self.grid[:, 0], self.grid[:, 1]
        strata_uv = np.stack([u, np.cos(2 * math.pi * v), np.sin(2 * math.pi * v), 0 * u], 1)
        interleaved = self.sets is not None
        return {**points, "device": device, "strata_uv": buf(strata_uv),
                "classes": points["classes"] if interleaved else buf([0], np.uint8),
                "sets": buf(self.sets if interleaved else [0], np.int32),
                "table": buf(table), "table_n": np.int32(table.size),
                "kernel": _sample_kernel(device, self.light.kind, self.count, interleaved)}

    def close(self) -> None:
        """Let the device buffers go (a light's sampler is done once its rays are)."""
        self.device = None

    def entering_sample(self, k: int, rays_into: tuple[NDArray[np.float32], NDArray[np.float32]]
                        | None = None, span: tuple[int, int] | None = None
                        ) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
        """:meth:`sample` with the weight times the fraction entering the skin,
        T(n . d) (:func:`~.boundary.transmission`), and the shadow ray's length 0 where the
        weight is
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
            enters = transmission_lookup(np.einsum("ij,ij->i", self.normals, d), self.eta)
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
        device = dev["device"]
        queue = device.queue
        # each sample's own arrays, written in place on a CPU device (a copy out of
        # device buffers took 1.3-2.9 ms of a sample's 4-7 at texture 1024)
        buffers = [host_output(device, a) for a in out]
        with _SAMPLE_LOCK:  # a kernel object's arguments are shared: one launch at a time
            dev["kernel"](queue, (-(-n // SAMPLE_POINTS_PER_ITEM),), None, dev["origin"],
                          dev["normal"], dev["strata_uv"], dev["classes"], dev["sets"],
                          *self._sphere, dev["table"], dev["table_n"], np.int32(k), *buffers,
                          np.int32(n), np.int32(first))
        for buffer, array in zip(buffers, out, strict=True):
            read_output(device, buffer, array)
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
        numpy: a sampler made without a device, or of a kind the device does not
        sample)."""
        if self.device is not None:
            raise InputError(f"light {self.light.path}: sampled on the device "
                             "(entering_sample); make the sampler without a device")
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


def light_rng(seed: int, light: Light) -> np.random.Generator:
    """The random numbers of one light's samples: the same for the light in every call
    (its samples' grid), whatever other lights are sampled with it."""
    return np.random.default_rng([seed, zlib.crc32(light.path.encode())])


def is_delta_light(light: Light) -> bool:
    """A light of zero extent: a distant light of angle 0 or a sphere of radius 0."""
    return (light.kind == "distant" and light.angle_deg <= 0.0) or \
        (light.kind == "sphere" and light.radius <= 0.0)
