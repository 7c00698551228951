"""What a frame's tasks hand each other: the task log for ``render.json``, the camera's
hits, and each skin mesh's texture-space maps as the tasks fill and release them."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from .bands import BAND_ITEMS, in_bands
from .diffusion.surface_terms import SurfaceLight
from .scene import SceneMesh
from .shading import albedo_texture
from .surface.texture_maps import (
    TextureMaps,
)


class _BothArrived:
    """Calls ``then`` once both the irradiance and the layout have arrived (each counts
    once, from any thread)."""

    def __init__(self, then: Callable[[], None]) -> None:
        self._then = then
        self._lock = threading.Lock()
        self._waiting = {"irradiance", "layout"}

    def arrive(self, party: str) -> None:
        with self._lock:
            if party not in self._waiting:
                return
            self._waiting.discard(party)
            last = not self._waiting
        if last:
            self._then()


@dataclass
class TaskLog:
    seconds: dict[str, float] = field(default_factory=dict)
    cached: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    measures: dict[str, Any] = field(default_factory=dict)


class CameraHits(NamedTuple):
    """What a render's camera sees (:meth:`Renderer._camera_hits`): rays through the
    pixel centres (origins, unit directions) and their first hits (triangle or -1,
    barycentric u, v, distance), the silhouette pixels' flat indices and their extra
    rays and hits."""

    origins: NDArray[np.float64]
    dirs: NDArray[np.float64]
    hits: tuple[NDArray[Any], ...]
    edge: NDArray[np.intp]
    edge_origins: NDArray[np.float64]
    edge_dirs: NDArray[np.float64]
    edge_hits: tuple[NDArray[Any], ...]


@dataclass
class SkinTextures:
    """Texture-space results of one skin mesh."""

    mesh: SceneMesh
    uv: NDArray[np.float64]
    uv_tris: NDArray[np.int32]
    tris: NDArray[np.int32]
    maps: TextureMaps
    albedo: NDArray[np.float32] | None = None
    """The albedo map (:func:`albedo_texture`), made only for a split whose powers
    :func:`~.resample.times_resampled_power` does not take as numpy does
    (:meth:`Renderer.albedo`)."""
    albedo_image: NDArray[np.float32] | None = None
    """The albedo's own image (:func:`albedo_image`; after the irradiance, which does not
    read it): the split's weights and the shading's lookups are made from it, the same
    floats as from the map, without the map (201 MB at texture 4096)."""
    irradiance_filled: NDArray[np.float32] | None = None  # seams filled, for lookups
    visibility: dict[str, NDArray[np.float32]] = field(default_factory=dict)
    radiance: NDArray[np.float32] | None = None
    """The diffused radiance of the terms blurred in the charts' tiles (H, W, 3)."""
    surface_light: SurfaceLight | None = None
    """The wide terms' light, summed on the surface and read at the camera's hits
    (:mod:`~.diffusion.surface_terms`; x albedo^(1 - split) / pi there)."""
    radiosity: NDArray[np.float32] | None = None
    """All the terms' radiance at the texels, for the radiosity texture output."""
    period: int = 2
    """The interleaving period of its shadow rays (:meth:`Renderer._interleaving`)."""
    texels_per_pixel: float = 0.0
    """Texels across an image pixel at the skin (:func:`texels_per_pixel`; 0: unknown)."""
    keys: dict[str, str] = field(default_factory=dict)
    """Cache keys of the texture maps, albedo and irradiance: what later tasks key on,
    instead of hashing the maps themselves."""
    at_hits: dict[str, dict[str, NDArray[np.float32]]] | None = None
    """The irradiance (N, 3), the albedo (N, 3) and each light's visibility (N,) looked up
    at the camera's hits on this mesh, 'center' and 'edge' rays
    (:meth:`Renderer._look_up_at_hits`; what the AOVs asked for need):
    taken before the diffusion in a render's last frame, so that the maps could go
    (None: the shading looks them up in the maps)."""
    hit_uv: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    """The texture coordinates of those hits, by part, where they were taken: the
    shading reads them rather than making them again."""

    def albedo_map(self) -> NDArray[np.float32]:
        """The albedo map: the one made, else one made now from the image."""
        if self.albedo is not None:
            return self.albedo
        assert self.albedo_image is not None
        return albedo_texture(self.albedo_image, self.maps.triangle.shape[0])

    @property
    def irradiance(self) -> NDArray[np.float32] | None:
        """The irradiance (H, W, 3), 0 off the charts, as a new array: the filled one where
        a triangle covers the texel, which the push-pull and the gutter leave as it was
        (a copy kept beside the filled one held 201 MB at texture 4096)."""
        filled = self.irradiance_filled
        if filled is None:
            return None
        triangle = self.maps.triangle
        out = np.empty(filled.shape, np.float32)

        def band(rows: slice) -> None:  # in bands on the cores: half the time
            np.copyto(out[rows], np.where((triangle[rows] >= 0)[..., None], filled[rows],
                                          np.float32(0.0)))

        in_bands(band, out.shape[0], BAND_ITEMS // max(out.shape[1], 1))
        return out


def hit_uvs(tex: SkinTextures, tri_idx: NDArray[Any], b: NDArray[Any]) -> NDArray[np.float64]:
    """Texture coordinates (N, 2) of hits on ``tex``'s mesh: triangles ``tri_idx``,
    barycentrics ``b`` (N, 3, 1), as :func:`mesh_hits` gives them."""
    return (tex.uv[tex.uv_tris[tri_idx]] * b).sum(axis=1)
