"""Where obliquely entering light first scatters.

The diffusion spreads each texel's light by the profile a pencil beam gives at normal
incidence, centred where the light entered. Light that enters at an angle runs along its
refracted direction before it first scatters, a mean 1 / sigma_t' (the reduced
extinction: the similarity relation's), so what it gives back is centred that far
downstream, sin(theta_t) / sigma_t' along the surface: the centroid shift of
oblique-incidence reflectometry (Wang & Jacques 1995, Appl. Opt. 34(13), with the
diffusion source one transport length deep). On a flat, evenly lit surface that moves
nothing; at a shadow edge or a curved surface's terminator, where the light entering
changes within a transport length, it carries light across (docs/render.md: a sphere's
terminator against Mitsuba 3).

What enters also has to stay in: on a convex part the refracted path leaves the skin
again after a chord L, and only 1 - exp(-sigma_t' L) of the light scatters before it
does (the rest goes through unscattered and is not diffuse light). Near a terminator the
chords are short.

So each texel p takes, for each light (domes aside: light from every side moves every
way at once) and channel, the light that entered upstream of it: at the surface under
p - shift, shift = (sin theta_t / sigma_t') t, t the refracted direction's unit
tangent (Embree, along -n, from the tangent plane), its entering irradiance read
bilinearly over covered texels, times that entry's 1 - exp(-sigma_t' L). sin theta_t
is the light's at p (sin theta_i / eta; 1 / eta past the terminator, where p's own
light is grazing at most). The medium is each region's inverted one, as for the thin
parts (:mod:`.thin_parts`). Left out: the source's depth (cos theta_t / sigma_t'
rather than 1 / sigma_t': the angular law, :mod:`.reflection_law`, keeps the total);
the chord's truncation of the mean path (measured: it moves the sphere's 10% points
0.2-0.3 mm past the path tracer's).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..bands import band_slices
from ..device.choice import Device
from ..device.memory import run_on_host_arrays
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from ..surface.texture_maps import texels_per_scene_unit, triangle_jacobians
from .irradiance import IrradianceResult, coloured
from .raytrace import RayScene, exit_distances, face_normals
from .samples import Light, light_direction
from .thin_parts import BAND_POINTS, FarSide, with_far_side

FloatArray = NDArray[np.float64]

_UPSTREAM_KERNEL = cl_source(__package__, "first_scatter.cl")

CHORD_OPTICAL_DEPTH = math.log(1e4)
"""Chords are traced this many mean free paths (sigma_t' L) deep, no farther: past it a
ten-thousandth of the light leaves unscattered, and Embree leaves the rest of the head
unvisited (at texture 4096 on the demo face the chords took 1.9 s a light)."""


@lru_cache(maxsize=4)
def _upstream_kernel(device: Device) -> Kernel:
    return Kernel(build(device, _UPSTREAM_KERNEL), "upstream_read", 1)


def light_centre(light: Light) -> tuple[bool, NDArray[np.float64]]:
    """Whether ``light`` is seen from a point (its centre's position) or is distant (the
    direction towards it), and that vector: what :func:`~.samples.light_direction`
    takes the direction from."""
    if light.kind == "distant":
        return False, -np.asarray(light.axis, np.float64)
    return True, np.asarray(light.position, np.float64)


def _channel_max(rgb: NDArray[Any]) -> NDArray[Any]:
    """(N,) the largest of each row of (N, 3): by columns (a reduction along the short
    axis took 16x as long, 0.3 s a light at texture 4096)."""
    return np.maximum(np.maximum(rgb[:, 0], rgb[:, 1]), rgb[:, 2])


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.einsum("ij,ij->i", a, b)


def refracted_into(towards_light: FloatArray, normals: FloatArray, eta: float) -> FloatArray:
    """Unit directions light from ``towards_light`` travels in after the boundary of
    relative index ``eta`` (Snell), for points that face the light."""
    cos_i = np.clip(_dot(towards_light, normals), 0.0, 1.0)[:, None]
    cos_t = np.sqrt(np.clip(1.0 - (1.0 - cos_i**2) / eta**2, 0.0, 1.0))
    return -towards_light / eta + (cos_i / eta - cos_t) * normals


def upstream_shift(towards_light: FloatArray, normals: FloatArray, eta: float,
                   mean_path: FloatArray) -> FloatArray:
    """(N, 3) the vector in the tangent plane from each point to where the light it first
    scatters under entered: towards the light, of length sin(theta_t) x ``mean_path``
    (N,). Past the terminator sin(theta_i) is 1."""
    tangent = towards_light - _dot(towards_light, normals)[:, None] * normals
    length = np.linalg.norm(tangent, axis=1)
    sin_i = np.where(_dot(towards_light, normals) >= 0.0, length, 1.0)
    return tangent * (sin_i / eta * mean_path / np.maximum(length, 1e-12))[:, None]


@dataclass(frozen=True)
class SurfaceReads:
    """Where points read a texture: per point four texel rows (-1: none) and their
    bilinear weights, renormalised over the covered ones (rows with no weight read
    nothing)."""

    rows: NDArray[np.int64]  # (N, 4)
    weights: NDArray[np.float32]  # (N, 4)

    def read(self, values: NDArray[np.float32], own: NDArray[np.float32]) -> NDArray[np.float32]:
        """``values`` (M,) at the reads, or ``own`` (N,) where a point reads nothing."""
        out = np.zeros(self.rows.shape[0], np.float32)
        for k in range(4):
            r = self.rows[:, k]
            out += self.weights[:, k] * values[np.maximum(r, 0)] * (r >= 0)
        return np.where(self.weights.sum(axis=1) > 0, out, own)


def texel_reads(at_texels: FloatArray, row_of: NDArray[np.int32], size: int) -> SurfaceReads:
    """Bilinear reads at texture coordinates in texels (K, 2) of rows ``row_of`` (flat
    texel -> row, -1 off the charts)."""
    f = at_texels - 0.5
    x0, y0 = np.floor(f[:, 0]).astype(np.int64), np.floor(f[:, 1]).astype(np.int64)
    tx, ty = f[:, 0] - x0, f[:, 1] - y0
    rows, weights = [], []
    for dx, dy, w in ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)),
                      (0, 1, (1 - tx) * ty), (1, 1, tx * ty)):
        x, y = np.clip(x0 + dx, 0, size - 1), np.clip(y0 + dy, 0, size - 1)
        r = row_of[y * size + x].astype(np.int64)
        rows.append(r)
        weights.append(np.where(r >= 0, w, 0.0))
    rw, ww = np.stack(rows, axis=1), np.stack(weights, axis=1)
    total = ww.sum(axis=1, keepdims=True)
    ww = np.where(total > 1e-6, ww / np.maximum(total, 1e-12), 0.0)
    return SurfaceReads(rw, ww.astype(np.float32))


def surface_reads(rays: RayScene, mesh_index: int, uv: FloatArray,
                  uv_tris: NDArray[np.integer], size: int, row_of: NDArray[np.int32],
                  points: FloatArray, normals: FloatArray, shift: FloatArray,
                  lift: FloatArray) -> SurfaceReads:
    """Where the skin lies under ``points + shift`` (N, 3), projected along -normal from
    ``lift`` (N,) above (Embree; a concave surface lies under the tangent plane), as
    :func:`texel_reads`; points whose projection misses this mesh read nothing."""
    lift = lift[:, None] * normals
    prim, u, v, _ = rays.intersect(np.asarray(points + shift + lift, np.float32),
                                   np.asarray(-normals, np.float32))
    hit = np.flatnonzero(prim >= 0)
    owner = rays.owner[prim[hit]]
    own = owner[:, 0] == mesh_index
    hit, local = hit[own], owner[own, 1]
    corners = np.asarray(uv, np.float64)[np.asarray(uv_tris).reshape(-1, 3)[local]]
    a, b = u[hit, None].astype(np.float64), v[hit, None].astype(np.float64)
    at = (corners[:, 0] * (1 - a - b) + corners[:, 1] * a + corners[:, 2] * b) * size
    found = texel_reads(at, row_of, size)
    rows = np.full((points.shape[0], 4), -1, np.int64)
    weights = np.zeros((points.shape[0], 4), np.float32)
    rows[hit], weights[hit] = found.rows, found.weights
    return SurfaceReads(rows, weights)


@dataclass(frozen=True)
class FirstScatter:
    """A skin mesh's surface and medium for :meth:`upstream`: the covered texels (flat
    indices ``texel`` of a ``size`` texture), their triangles (local to ``mesh_tris``),
    points and normals (N, 3), each one's reduced extinction sigma_t' (N, 3, per scene
    unit), and the boundary's index."""

    rays: RayScene
    mesh_index: int
    mesh_points: FloatArray
    mesh_tris: NDArray[np.integer]
    uv: FloatArray
    uv_tris: NDArray[np.integer]
    size: int
    texel: NDArray[np.intp]
    triangles: NDArray[np.int32]
    points: NDArray[np.float32]
    normals: NDArray[np.float32]
    reduced_extinction: NDArray[np.float32]
    eta: float
    device: Device

    @cached_property
    def _texels_per_length(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Per triangle the map of a vector in its plane (scene units) to texels (T, 6:
        :func:`~..surface.texture_maps.texels_per_scene_unit`) and a texel's size in
        scene units, sqrt |J_x x J_y| (T,; 0 where the triangle is degenerate)."""
        _, _, jac = triangle_jacobians(self.mesh_points, np.asarray(self.mesh_tris),
                                       self.uv, np.asarray(self.uv_tris).reshape(-1, 3),
                                       self.size)
        size = np.sqrt(np.linalg.norm(np.cross(jac[:, :, 0], jac[:, :, 1]), axis=1))
        return (np.ascontiguousarray(texels_per_scene_unit(jac).reshape(-1, 6), np.float32),
                size.astype(np.float32))

    def upstream(self, light: Light, entering: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N, 3) the light ``light`` gave (``entering``, (N, 3), shadowed) as it first
        scatters: :meth:`scattering`, read from where it entered upstream
        (:meth:`read_upstream`)."""
        return self.read_upstream(light, self.scattering(light, entering))

    @cached_property
    def _row_of(self) -> NDArray[np.int32]:
        """Each flat texel's row (-1 off the charts)."""
        row_of = np.full(self.size * self.size, -1, np.int32)
        row_of[self.texel] = np.arange(self.texel.size, dtype=np.int32)
        return row_of

    def scattering(self, light: Light, entering: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N, 3) ``entering`` times the share that scatters before its refracted path
        leaves the skin again, 1 - exp(-sigma_t' L) for the chord L (Embree)."""
        out = np.array(entering, np.float32, copy=True)
        faces = face_normals(self.mesh_points, self.mesh_tris)
        for band in band_slices(out.shape[0], BAND_POINTS):  # a band's arrays at a time
            lit = np.flatnonzero(_channel_max(entering[band]) > 0) + band.start  # can lose light
            p = np.take(self.points, lit, axis=0)
            nrm = np.take(self.normals, lit, axis=0)
            w = np.asarray(light_direction(light, p)[0], np.float32)
            sigma = self.reduced_extinction[lit]
            deepest = CHORD_OPTICAL_DEPTH / np.maximum(-_channel_max(-sigma), 1e-30)
            chord = exit_distances(self.rays, self.mesh_index, self.mesh_points,
                                   self.mesh_tris, p, nrm, refracted_into(w, nrm, self.eta),
                                   faces, deepest)
            ends = np.isfinite(chord)  # an open scan's paths mostly leave nowhere
            lit, chord = lit[ends], chord[ends]
            out[lit] *= -np.expm1(-sigma[ends] * chord[:, None])
        return out

    def read_upstream(self, light: Light, values: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N, 3) ``values`` (N, 3) read per channel where the light first scattering at
        each point entered: in the point's own chart through its triangle's map to
        texels, on the device, where the texel found there lies within a quarter of the
        shift (or two texels) of the shifted point; elsewhere (a seam, a fold, a
        chart's edge) projected on the skin by Embree (:func:`surface_reads`)."""
        n_points = self.texel.size
        row_of = self._row_of
        k, texel_length = self._texels_per_length
        kernel = _upstream_kernel(self.device)
        out = np.empty((n_points, 3), np.float32)
        cast = np.empty((n_points, 3), np.uint8)
        mean_path = 1.0 / np.asarray(self.reduced_extinction, np.float32)
        at_point, vector = light_centre(light)
        for band in band_slices(n_points, BAND_POINTS):  # a band's arrays at a time
            got = np.empty((band.stop - band.start, 3), np.float32)
            flags = np.empty((band.stop - band.start, 3), np.uint8)
            run_on_host_arrays(
                kernel, self.device, (band.stop - band.start,),
                [row_of, np.int32(self.size), np.asarray(self.texel[band], np.int32),
                 np.asarray(self.triangles[band], np.int32), k, texel_length,
                 np.asarray(self.points, np.float32), np.int32(at_point),
                 *np.asarray(vector, np.float32), np.asarray(self.normals[band], np.float32),
                 np.ascontiguousarray(mean_path[band]), np.float32(self.eta),
                 np.int32(band.start), np.asarray(values, np.float32),
                 np.int32(band.stop - band.start)],
                [got, flags])
            out[band], cast[band] = got, flags
        for c in range(3):
            at = np.flatnonzero(cast[:, c])
            if not at.size:
                continue
            p = np.asarray(self.points[at], np.float64)
            nrm = np.asarray(self.normals[at], np.float64)
            path = np.asarray(mean_path[at, c], np.float64)
            shift = upstream_shift(light_direction(light, p)[0], nrm, self.eta, path)
            reads = surface_reads(self.rays, self.mesh_index, self.uv, self.uv_tris,
                                  self.size, row_of, p, nrm, shift, path)
            out[at, c] = reads.read(values[:, c], values[at, c])
        return out


def through_volume(entering: NDArray[np.float32], first: FirstScatter | None,
                   far: FarSide | None, lights: Sequence[Light], result: IrradianceResult,
                   visibility: Mapping[str, NDArray[Any]], measures: dict[str, Any]
                   ) -> NDArray[np.float32]:
    """``entering`` (N, 3) with each light's but domes' (light from every side moves
    every way at once) moved to where it first scatters (:func:`with_first_scatter`, its
    light its unshadowed irradiance in ``result`` times ``visibility``; timed into
    ``measures``) and the thin parts' far sides' light added (:func:`~.thin_parts.
    with_far_side`, read as it entered: the slabs' table holds all that enters the
    back)."""
    out = entering
    if first is not None:
        start = time.perf_counter()
        moved = [light for light in lights
                 if light.kind != "dome" and light.path in result.unshadowed]
        out = with_first_scatter(entering, first, (
            (light, coloured(*result.unshadowed[light.path])
             * np.asarray(visibility[light.path], np.float32)[:, None]) for light in moved))
        measures["first_scatter"] = {"lights": len(moved),
                                     "seconds": time.perf_counter() - start}
    return out if far is None else with_far_side(out, far, entering)


def with_first_scatter(entering: NDArray[np.float32], first: FirstScatter,
                       lights: Iterable[tuple[Light, NDArray[np.float32]]]
                       ) -> NDArray[np.float32]:
    """``entering`` (N, 3) with each of ``lights``' own share ((light, its entering
    irradiance (N, 3)) pairs) replaced by :meth:`FirstScatter.upstream`'s."""
    out = np.array(entering, np.float32, copy=True)
    for light, own in lights:
        out += first.upstream(light, own)
        out -= own
    return np.maximum(out, 0.0, out=out)  # what was subtracted rounds below 0
