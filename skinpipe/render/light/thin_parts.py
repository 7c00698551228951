"""Light through thin parts of the skin: what enters one side of an ear, a nostril's
rim or a slab and leaves the other, through the volume, which texture-space diffusion
(light carried along the surface only) cannot carry.

Per covered texel a ray goes into the skin along -n to where it leaves the mesh again
(Embree; the first hit on the same skin mesh, from inside, within the thickness the
medium lets light through): the back point and the thickness d between them. The light
the back point receives (its irradiance, every light of the scene, as the texture-space
irradiance holds it) crosses the slab of thickness d and leaves the front with the
transmission of that region's medium, pi L / E = T(alpha', sigma_t' d): an index-matched
slab lit uniformly from behind, seen from straight above, tabulated by the tests' light
tracer (slab_transmission_table.py) at the similarity relation's reduced albedo and
thickness. It is added to the front texel's irradiance over the mesh's mean albedo, so
that the diffusion (which multiplies by the albedo) spreads it over the front as the
profile spreads light: the transmitted light leaves within about d of the back point's
opposite, the profile's own width at skin's thicknesses.

The medium of each region is the one its profile inverts to (:mod:`skinpipe.profile.
medium`, as OpenPBR gets it). What it leaves out: the back's own light is not reduced
by what goes through (a thin slab reflects less than a thick one); the slab is taken as
locally flat and uniformly lit; a boundary's Fresnel loss is in the medium as inverted,
not modelled twice.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...profile.medium import MediumEstimate, similarity_relation
from ..bands import band_slices
from . import slab_transmission_table as TABLE
from .raytrace import RayScene, exit_distances, face_normals, hits_leaving
from .samples import orthonormal_frame

_S = np.asarray(TABLE.S_GRID)
_LOG_TAU = np.log(np.asarray(TABLE.TAU_GRID))
_LOG_T = np.log(np.maximum(np.asarray(TABLE.TRANSMISSION), 1e-12))

FloatArray = NDArray[np.float64]


def slab_transmission(reduced_albedo: ArrayLike, optical_thickness: ArrayLike) -> FloatArray:
    """T = pi L / E of the table: bilinear in (s, log tau) of log T, s = sqrt(1 - alpha');
    beyond the thickest slab the last two columns' exponential fall is carried on, below
    the thinnest T goes to 0 with tau."""
    s = np.clip(np.sqrt(np.clip(1.0 - np.asarray(reduced_albedo, np.float64), 0.0, 1.0)),
                _S[0], _S[-1])
    tau = np.maximum(np.asarray(optical_thickness, np.float64), 1e-9)
    s, tau = np.broadcast_arrays(s, tau)
    shape = s.shape
    s, tau = s.reshape(-1), tau.reshape(-1)
    i = np.clip(np.searchsorted(_S, s) - 1, 0, _S.size - 2)
    fs = (s - _S[i]) / (_S[i + 1] - _S[i])
    x = np.log(tau)
    j = np.clip(np.searchsorted(_LOG_TAU, x) - 1, 0, _LOG_TAU.size - 2)
    fx = (x - _LOG_TAU[j]) / (_LOG_TAU[j + 1] - _LOG_TAU[j])

    def at(jj: NDArray[np.intp], f: FloatArray) -> FloatArray:
        return (1 - fs) * ((1 - f) * _LOG_T[i, jj] + f * _LOG_T[i, jj + 1]) \
            + fs * ((1 - f) * _LOG_T[i + 1, jj] + f * _LOG_T[i + 1, jj + 1])

    first = np.exp(at(np.zeros_like(j), np.zeros_like(fx))) * tau / math.exp(_LOG_TAU[0])
    out = np.where(x < _LOG_TAU[0], first, np.exp(at(j, fx)))
    return out.reshape(shape)


@dataclass(frozen=True)
class ThinMedia:
    """Per region (R) and channel (3): the reduced albedo alpha' and the reduced
    extinction sigma_t' (per scene unit), and the mesh's mean albedo (3,)."""

    reduced_albedo: FloatArray
    reduced_extinction: FloatArray
    mean_albedo: FloatArray

    @classmethod
    def of(cls, media: Sequence[MediumEstimate], mean_albedo: ArrayLike,
           meters_per_unit: float) -> ThinMedia:
        """From each region's medium."""
        a = np.array([m.single_scattering_albedo for m in media], np.float64).reshape(-1, 3)
        g = np.array([m.anisotropy for m in media], np.float64).reshape(-1, 1)
        sigma_t = 1.0 / np.array([m.mean_free_path_mm for m in media],
                                 np.float64).reshape(-1, 3)
        per_unit = meters_per_unit * 1000.0  # mm a scene unit
        reduced, factor = similarity_relation(a, g)
        return cls(reduced, sigma_t * factor * per_unit,
                   np.maximum(np.asarray(mean_albedo, np.float64), 1e-4))

    @cached_property
    def reach(self) -> float:
        """The thickness (scene units) beyond which no region lets a thousandth of its
        albedo through."""
        tau = np.asarray(TABLE.TAU_GRID)
        t = slab_transmission(self.reduced_albedo[..., None], tau)  # (R, 3, taus)
        past = (t / self.mean_albedo[None, :, None] > 1e-3).any(axis=(0, 1))
        last = tau[np.flatnonzero(past)[-1]] if past.any() else tau[0]
        return float(last / self.reduced_extinction.min())

    def extinction_at(self, weights: NDArray[Any] | None, points: int) -> NDArray[np.float32]:
        """(N, 3) the reduced extinction at ``points`` points, the regions blended by
        ``weights`` (N, R) (None: their mean)."""
        if weights is None:
            return np.tile(self.reduced_extinction.mean(axis=0), (points, 1)).astype(np.float32)
        return np.asarray(weights, np.float32) @ self.reduced_extinction.astype(np.float32)

    def through(self, thickness: FloatArray, weights: FloatArray | None) -> FloatArray:
        """(N, 3) what a back point's irradiance is worth at the front, over the mean
        albedo, for ``thickness`` (N,) scene units, the regions blended by ``weights``
        (N, R) (None: equally)."""
        d = np.asarray(thickness, np.float64)
        n_regions = self.reduced_albedo.shape[0]
        w = np.full((d.size, n_regions), 1.0 / n_regions) if weights is None else \
            np.asarray(weights, np.float64).reshape(d.size, n_regions)
        out = np.zeros((d.size, 3))
        for r in range(n_regions):
            t = slab_transmission(self.reduced_albedo[r][None, :],
                                  self.reduced_extinction[r][None, :] * d[:, None])
            out += w[:, r, None] * t
        return out / self.mean_albedo


BAND_POINTS = 1 << 20
"""Points whose rays into the skin go to Embree at once: the rays' arrays are a band's,
not the texture's (at texture 4096 the whole texture's held 1 GB at the render's peak),
and what is kept is the few points with a far side."""


@dataclass(frozen=True)
class FarSide:
    """The points (rows) that have a far side within reach: each one's row of the far
    side's texel and what that texel's irradiance is worth there (K, 3)."""

    rows: NDArray[np.int64]
    far_rows: NDArray[np.int64]
    factor: NDArray[np.float32]


def back_points(rays: RayScene, mesh_index: int, mesh_points: FloatArray,
                mesh_tris: NDArray[np.integer], points: FloatArray, normals: FloatArray,
                reach: float) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray,
                                       FloatArray]:
    """The points (indices into ``points``) where a ray into the skin along -normal leaves
    the same mesh within ``reach``: those indices, the skin triangle hit (local index into
    ``mesh_tris``), its barycentrics (K, 2) and the distance. A hit from outside (a fold,
    another part in the way) is none. In bands of :data:`BAND_POINTS` points."""
    faces = face_normals(mesh_points, mesh_tris)
    found: list[tuple[NDArray[np.int64], ...]] = []
    for band in band_slices(points.shape[0], BAND_POINTS):
        n = np.asarray(normals[band], np.float32)
        # rays end at the reach: Embree then leaves the rest of the head unvisited
        hit, local, u, v, dist = hits_leaving(rays, mesh_index, faces, points[band], n, -n,
                                              reach)
        keep = dist <= reach
        found.append((hit[keep] + band.start, local[keep],
                      np.stack([u[keep], v[keep]], axis=1), dist[keep].astype(np.float64)))
    if not found:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)),
                np.zeros(0))
    index, tri, bary, thickness = (np.concatenate(parts) for parts in zip(*found,
                                                                           strict=True))
    return index.astype(np.int64), tri.astype(np.int64), bary.astype(np.float64), thickness


ROUNDNESS_TILT = math.radians(45.0)
"""How far from -n the rays that tell a round part from a flat one are tilted."""


def flatness(rays: RayScene, mesh_index: int, mesh_points: FloatArray,
             mesh_tris: NDArray[np.integer], points: FloatArray, normals: FloatArray,
             thickness: FloatArray) -> FloatArray:
    """(K,) 1 where the part under ``points`` is a slab, 0 where it is round: a chord
    tilted by a from -n is d / cos a through a slab and d cos a through a ball or across
    a tube; the shorter of two tilted chords (along two tangents) maps linearly from
    d cos a -> 0 to d / cos a -> 1. Round, light reaches the far side round the
    surface, which the diffusion carries along it already."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    frame = orthonormal_frame(n)
    t1, t2 = frame[:, 0], frame[:, 1]
    c, s = math.cos(ROUNDNESS_TILT), math.sin(ROUNDNESS_TILT)
    faces = face_normals(mesh_points, mesh_tris)
    shortest = np.minimum(*(exit_distances(rays, mesh_index, mesh_points, mesh_tris, p, n,
                                           -c * n + s * t, faces) for t in (t1, t2)))
    ratio = shortest / np.maximum(np.asarray(thickness, np.float64), 1e-30)
    return np.clip((ratio - c) / (1.0 / c - c), 0.0, 1.0)


PROBE_TEXTURE_SIZE = 1024
"""Above this texture size the rays along -n first go from one texel in each block of
size / 1024 texels a side (as many as a texture-1024 render casts), then from every
texel in and beside the blocks where one found a far side: the demo face at texture
4096 has one in 0.2% of its texels, and rays from all of them took 0.9 s. Far sides
no probe within :data:`PROBE_RING_BLOCKS` blocks sees are missed: on the demo face at
texture 4096, 162 of its 31852 far-side texels."""


PROBE_RING_BLOCKS = 2
"""The blocks round one whose probe found a far side that cast from every texel too."""


def _rows_to_cast(row_of: NDArray[np.int32],
                  cast: Callable[[NDArray[np.int64]], tuple[NDArray[Any], ...]]
                  ) -> NDArray[np.int64] | None:
    """The rows (ascending) whose rays :func:`far_side` casts, for a texture of each
    texel's row ``row_of`` (size, size; -1 off the charts), ``cast`` giving the rows
    with a far side among rows it is given; None: every row (a texture no larger than
    :data:`PROBE_TEXTURE_SIZE`)."""
    size = row_of.shape[0]
    block = size // PROBE_TEXTURE_SIZE
    if block <= 1:
        return None
    probes = row_of[::block, ::block]
    probe_rows = probes[probes >= 0].astype(np.int64)
    near = np.zeros(probes.shape, bool)
    near.flat[np.flatnonzero(probes >= 0)[np.isin(probe_rows, cast(probe_rows)[0])]] = True
    from scipy.ndimage import binary_dilation  # lazy, as chart_tiles' filters

    # and the blocks round: a far side's edge may lie in a block whose probe missed it
    side = 2 * PROBE_RING_BLOCKS + 1
    near = binary_dilation(near, np.ones((side, side), bool))
    rows = row_of[np.repeat(np.repeat(near, block, axis=0), block, axis=1)[:size, :size]]
    return rows[rows >= 0].astype(np.int64)


def far_side(rays: RayScene, mesh_index: int, mesh_points: FloatArray,
             mesh_tris: NDArray[np.integer], uv: FloatArray, uv_tris: NDArray[np.integer],
             size: int, points: FloatArray, normals: FloatArray, texel: NDArray[np.intp],
             media: ThinMedia, regions: NDArray[Any] | None) -> FarSide:
    """For covered texels (flat indices ``texel`` of a ``size`` texture, at ``points`` with
    ``normals``) those whose far side (:func:`back_points`) is a covered texel: their
    rows, the far texel's row and what its irradiance is worth here, the regions blended
    by ``regions`` (N, R)."""
    row_of = np.full(size * size, -1, np.int32)  # 64 MB at texture 4096, not 128
    row_of[texel] = np.arange(texel.size, dtype=np.int32)

    def cast(rows: NDArray[np.int64] | None) -> tuple[NDArray[Any], ...]:
        """:func:`back_points` of ``rows`` (None: all), as rows."""
        if rows is None:
            return back_points(rays, mesh_index, mesh_points, mesh_tris, points, normals,
                               media.reach)
        found = back_points(rays, mesh_index, mesh_points, mesh_tris, points[rows],
                            normals[rows], media.reach)
        return (rows[found[0]], *found[1:])

    index, tri, bary, thickness = cast(_rows_to_cast(row_of.reshape(size, size), cast))
    if not index.size:
        return FarSide(index, index, np.zeros((0, 3), np.float32))
    corners = np.asarray(uv)[np.asarray(uv_tris)[tri]]  # (K, 3, 2)
    u, v = bary[:, 0:1], bary[:, 1:2]
    at_uv = corners[:, 0] * (1 - u - v) + corners[:, 1] * u + corners[:, 2] * v
    x, y = (np.clip((at_uv[:, k] * size).astype(np.int64), 0, size - 1) for k in (0, 1))
    far = row_of[y * size + x].astype(np.int64)
    del row_of
    covered = far >= 0
    index, far, thickness = index[covered], far[covered], thickness[covered]
    factor = media.through(thickness, None if regions is None else
                           np.asarray(regions[index], np.float64))
    factor *= flatness(rays, mesh_index, mesh_points, mesh_tris, points[index],
                       normals[index], thickness)[:, None]
    factor = factor.astype(np.float32)
    return FarSide(index, far, factor)


def with_far_side(entering: NDArray[np.float32], far: FarSide,
                  back: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """``entering`` (N, 3) irradiance rows plus, at each row of ``far``, its far side's
    row of ``back`` (the irradiance as it entered; default ``entering``) times its
    factor."""
    out = entering.copy()
    out[far.rows] += far.factor * (entering if back is None else back)[far.far_rows]
    return out
