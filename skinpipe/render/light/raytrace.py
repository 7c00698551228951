"""Ray queries with Embree (embreex): occlusion for shadows, first hits for the camera.

Embree drops triangles with non-finite or huge vertices or bad indices without a word,
and shadow rays then leak light; every mesh is validated before it enters the scene.
``EmbreeScene.run`` loops over rays serially but releases the GIL, so rays go out in
chunks on a few threads. Callers cast them in a coherent order, origins along a Morton
curve (:func:`morton_order`) or a texture's texels block by block
(:func:`~.texture_maps.texels_in_blocks`): neighbouring rays share BVH nodes in cache
(4.5x the rays a second of a random order on the face scan).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh
from numpy.typing import NDArray

from ...errors import InputError
from ...usd.mesh import MAX_COORDINATE
from ..bands import band_slices
from ..sorting import stable_order

CHUNK_RAYS = 65536


def _writable(a: NDArray[Any]) -> NDArray[np.float32]:
    # embreex takes typed memoryviews, which refuse read-only (e.g. broadcast) arrays
    return np.require(a, dtype=np.float32, requirements=["C", "W"])


_SPREAD_64 = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
              (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249))
_SPREAD_32 = ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249))


def _spread_bits3(q: NDArray[Any]) -> NDArray[Any]:
    """Insert two zero bits between each of the low bits of ``q`` (the "magic bits"
    Morton encoding): 21 bits of uint64, or 10 bits of uint32 (half the memory, four
    steps instead of five)."""
    wide = q.dtype == np.uint64
    t = q.dtype.type
    x = q & t(0x1FFFFF if wide else 0x3FF)
    for shift, mask in _SPREAD_64 if wide else _SPREAD_32:
        x = (x | (x << t(shift))) & t(mask)
    return x


OFFSET_ORIGIN = 1.0 / 32.0
OFFSET_FLOAT_SCALE = 1.0 / 65536.0
OFFSET_INT_SCALE = 256.0


OFFSET_ROWS = 16384
"""Points offset at a time: the temporaries stay in cache and are reused. Whole arrays'
took 0.85-0.9 s for the 7.7 M texels of the demo face at texture 4096 (their fresh pages
zeroed by the kernel, 0.3-0.65 s of it system time), these 0.25 s, bit for bit the same."""


def offset_ray_origin(points: NDArray[Any], normals: NDArray[Any]) -> NDArray[np.float32]:
    """Ray origins pushed off the surface along the normal by what the floating-point
    error of a float32 hit point needs (Wächter & Binder, "A Fast and Robust Method for
    Avoiding Self-Intersection", Ray Tracing Gems, 2019, listing 6-1): a fixed number of
    units in the last place of each coordinate, a fixed distance near zero. The offset
    follows the point's own magnitude, not the scene's size, so adding a far object
    moves no shadow."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.ascontiguousarray(normals, dtype=np.float32)
    if n.shape != p.shape:
        raise InputError(f"points and normals must agree; got {p.shape} and {n.shape}")
    out = np.empty_like(p)
    near = np.float32(OFFSET_FLOAT_SCALE)
    for s in range(0, p.shape[0], OFFSET_ROWS):
        pc, nc, oc = p[s:s + OFFSET_ROWS], n[s:s + OFFSET_ROWS], out[s:s + OFFSET_ROWS]
        # the integer offset, away from zero: against the point's sign where it is < 0
        of_i = (OFFSET_INT_SCALE * nc).astype(np.int32)
        np.negative(of_i, out=of_i, where=pc < 0)
        of_i += pc.view(np.int32)
        np.copyto(oc, of_i.view(np.float32))
        np.copyto(oc, pc + near * nc, where=np.abs(pc) < OFFSET_ORIGIN)
    return out


def morton_order(points: NDArray[Any], bits: int = 10) -> NDArray[np.int64]:
    """Indices that sort ``points`` (N, 3) along a 3D Morton (Z-order) curve with ``bits``
    (1-21) per axis."""
    if not 1 <= bits <= 21:
        raise ValueError(f"Morton bits must be 1-21, got {bits}")
    p = np.asarray(points)
    if p.size == 0:
        return np.zeros(0, np.int64)
    # one contiguous row per axis: numpy reduces and converts (N, 3) columns far slower
    real = np.float32 if bits <= 10 and p.dtype == np.float32 else np.float64
    rows = np.ascontiguousarray(p.T, dtype=real)
    lo, hi = rows.min(axis=1), rows.max(axis=1)
    scale = (((1 << bits) - 1) / np.maximum(hi - lo, 1e-30)).astype(real)
    # 32-bit codes for 30 bits; via signed integers, which numpy converts to far faster
    dtype = np.uint32 if bits <= 10 else np.uint64
    q = ((rows - lo[:, None]) * scale[:, None]).astype(
        np.int32 if bits <= 10 else np.int64).view(dtype)
    t = np.dtype(dtype).type
    code = _spread_bits3(q[0]) | (_spread_bits3(q[1]) << t(1)) | (_spread_bits3(q[2]) << t(2))
    return stable_order(code)


@dataclass
class RayStats:
    """Rays cast and the seconds spent, per query kind."""

    rays: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def add(self, kind: str, n: int, seconds: float) -> None:
        self.rays[kind] = self.rays.get(kind, 0) + n
        self.seconds[kind] = self.seconds.get(kind, 0.0) + seconds

    def mrays_per_s(self) -> dict[str, float]:
        return {k: self.rays[k] / max(self.seconds[k], 1e-9) / 1e6 for k in self.rays}


class RayScene:
    """Triangles from one or more meshes in one Embree scene. ``geometry`` maps each
    scene triangle back to (mesh index, triangle index within that mesh)."""

    def __init__(self, meshes: list[tuple[NDArray[Any], NDArray[Any]]],
                 threads: int | None = None) -> None:
        tri_points, owners = [], []
        for m, (points, tris) in enumerate(meshes):
            pts = np.asarray(points, dtype=np.float64)
            t = np.asarray(tris, dtype=np.int64)
            if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
                raise InputError(f"mesh {m}: points must be finite (N, 3)")
            if np.abs(pts).max(initial=0) > MAX_COORDINATE:
                raise InputError(f"mesh {m}: coordinates beyond {MAX_COORDINATE:g}")
            if t.size and (t.min() < 0 or t.max() >= pts.shape[0]):
                raise InputError(f"mesh {m}: triangle index out of range")
            tri_points.append(pts[t].astype(np.float32))
            owners.append(np.stack([np.full(t.shape[0], m), np.arange(t.shape[0])], axis=1))
        all_tris = np.concatenate(tri_points) if tri_points else np.zeros((0, 3, 3), np.float32)
        if all_tris.shape[0] == 0:
            raise InputError("the scene has no triangles to trace")
        self.scene = rtcs.EmbreeScene()
        self._mesh = TriangleMesh(self.scene, np.ascontiguousarray(all_tris))
        self.owner = np.concatenate(owners).astype(np.int64)
        extent = all_tris.reshape(-1, 3)
        self.diagonal = float(np.linalg.norm(extent.max(0) - extent.min(0)))
        self.threads = threads or min(4, os.cpu_count() or 1)
        self.stats = RayStats()

    def _chunks(self, n: int) -> list[slice]:
        return [slice(s, min(s + CHUNK_RAYS, n)) for s in range(0, n, CHUNK_RAYS)]

    def occluded(self, origins: NDArray[Any], directions: NDArray[Any],
                 max_distance: NDArray[Any] | float | None = None) -> NDArray[np.bool_]:
        """True where a ray from ``origins`` along unit ``directions`` hits anything before
        ``max_distance`` (scene units; default: beyond the scene). A ray of distance 0 or
        less is not traced (False, and not counted)."""
        n = origins.shape[0]
        out = np.zeros(n, dtype=bool)
        if n == 0:
            return out
        start = time.perf_counter()
        o = _writable(origins)
        d = _writable(directions)
        if max_distance is None or np.ndim(max_distance) == 0:
            far = np.full(n, 1e30 if max_distance is None else max_distance, np.float32)
        else:
            # the caller's lengths themselves when float32 (embreex only reads them; a
            # copy cost 0.3 ms of a sample at texture 1024)
            far = _writable(max_distance)
            if far.shape != (n,):
                raise InputError(f"max_distance must be ({n},), got {far.shape}")

        def run(s: slice) -> int:
            f = far[s]
            idle = ~(f > 0)
            idle_rays = int(np.count_nonzero(idle))
            if idle_rays:
                # Embree traverses a ray of length 0 like any other (its interval [0, 0]
                # holds the origin, which lies in the boxes around it: 89 against 80 ms
                # for the sphere light's sample at texture 1024, where 15% of the texels
                # face away); one whose far end is negative it takes as occluded already
                # and skips
                f = np.where(idle, np.float32(-1), f)
            hit = np.asarray(self.scene.run(o[s], d[s], query="OCCLUDED", dists=f)) >= 0
            out[s] = hit & ~idle if idle_rays else hit
            return f.size - idle_rays

        with ThreadPoolExecutor(self.threads) as pool:
            traced = sum(pool.map(run, self._chunks(n)))
        self.stats.add("occlusion", traced, time.perf_counter() - start)
        return out

    def intersect(self, origins: NDArray[Any], directions: NDArray[Any],
                  max_distance: NDArray[Any] | float | None = None
                  ) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32],
                             NDArray[np.float32]]:
        """First hits before ``max_distance`` (scene units, per ray or one for all;
        default: beyond the scene): (scene triangle or -1, barycentric u, v, distance).
        Embree leaves the boxes beyond a short ray's end unvisited."""
        n = origins.shape[0]
        start = time.perf_counter()
        o = _writable(origins)
        d = _writable(directions)
        prim = np.full(n, -1, np.int64)
        u = np.zeros(n, np.float32)
        v = np.zeros(n, np.float32)
        t = np.full(n, np.inf, np.float32)
        # a copy of the caller's lengths: embreex writes the hits' distances into them
        far = None if max_distance is None else \
            np.array(np.broadcast_to(np.asarray(max_distance, np.float32), (n,)))

        def run(s: slice) -> None:
            res = self.scene.run(o[s], d[s], output=1) if far is None else \
                self.scene.run(o[s], d[s], output=1, dists=far[s])
            prim[s] = res["primID"]
            u[s], v[s], t[s] = res["u"], res["v"], res["tfar"]

        with ThreadPoolExecutor(self.threads) as pool:
            list(pool.map(run, self._chunks(n)))
        self.stats.add("camera", n, time.perf_counter() - start)
        return prim, u, v, t


def face_normals(mesh_points: NDArray[np.float64], mesh_tris: NDArray[np.integer]
                 ) -> NDArray[np.float64]:
    """(T, 3) each triangle's unnormalised normal, by its winding."""
    verts = np.asarray(mesh_points, np.float64)[np.asarray(mesh_tris)]
    return np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])


def hits_leaving(rays: RayScene, mesh_index: int, faces: NDArray[np.float64],
                 points: NDArray[Any], normals: NDArray[Any], directions: NDArray[Any],
                 max_distance: NDArray[Any] | float | None = None
                 ) -> tuple[NDArray[np.intp], NDArray[Any], NDArray[Any], NDArray[Any],
                            NDArray[Any]]:
    """Rays from ``points`` (started just under the surface, along -``normals``) into
    the skin along ``directions`` whose first hit before ``max_distance`` (default: any)
    leaves the same mesh (``faces``: its :func:`face_normals`; a hit from outside, a
    fold or another part, is none): their indices, the triangle hit (local to the mesh),
    its barycentrics u, v and the distance."""
    d = np.asarray(directions, np.float32)
    prim, u, v, dist = rays.intersect(offset_ray_origin(points, -np.asarray(normals)), d,
                                      max_distance)
    hit = np.flatnonzero(prim >= 0)
    owner = rays.owner[prim[hit]]
    own = owner[:, 0] == mesh_index
    hit, local = hit[own], owner[own, 1]
    leaving = np.einsum("ij,ij->i", faces[local], np.asarray(d[hit], np.float64)) > 0
    hit, local = hit[leaving], local[leaving]
    return hit, local, u[hit], v[hit], dist[hit]


def exit_distances(rays: RayScene, mesh_index: int, mesh_points: NDArray[np.float64],
                   mesh_tris: NDArray[np.integer], points: NDArray[np.float64],
                   normals: NDArray[np.float64], directions: NDArray[np.float64],
                   faces: NDArray[np.float64] | None = None,
                   max_distance: NDArray[Any] | float | None = None) -> NDArray[np.float64]:
    """(N,) how far a ray into the skin along ``directions`` runs before it leaves the
    same mesh (inf where it does not: an open scan, a hit from outside, or not before
    ``max_distance``, per ray or one for all); ``faces``: the mesh's
    :func:`face_normals`, for callers that cast in bands."""
    faces = face_normals(mesh_points, mesh_tris) if faces is None else faces
    out = np.full(points.shape[0], np.inf)
    for band in band_slices(points.shape[0]):  # a band's arrays at a time
        hit, _, _, _, dist = hits_leaving(
            rays, mesh_index, faces, points[band], normals[band], directions[band],
            max_distance if max_distance is None or np.ndim(max_distance) == 0
            else np.asarray(max_distance)[band])
        out[band][hit] = dist
    return out
