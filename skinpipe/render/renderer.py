"""The renderer: a frame's tasks in order (unwrap, texture maps, irradiance, the seam
layout beside it, albedo, diffusion, camera hits, shading), each cached by the content of
its inputs so that a change re-runs only what depends on it (a camera move: only the
shading)."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, wait
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..imageio import (
    read_image,
)
from ..profile.medium import MediumEstimate
from .bands import beside, in_bands
from .device.choice import Device, open_device
from .device.huge_pages import apply_to_numpy, huge_pages_choice
from .device.programs import start_prewarm
from .diffusion.diffuse import diffuse_on_surface
from .diffusion.gather import diffuse_gather
from .diffusion.layout import (
    DiffusionLayout,
    chart_layout,
    release_freed_heap,
)
from .diffusion.push_pull import dilate_charts, prepare_dilation, push_pull
from .diffusion.surface_terms import texel_flux
from .diffusion.terms import DiffusionTerms, kept_diffusion_terms
from .diffusion.tile_store import TileStore
from .frame import CameraHits, SkinTextures, TaskLog, _BothArrived, hit_uvs
from .kernel_plan import kernel_plan
from .light.boundary import SkinBoundary, transmission
from .light.first_scatter import FirstScatter, through_volume
from .light.interleave import (
    interleave_classes,
    interleaved_visibility,
    texels_per_pixel,
)
from .light.irradiance import (
    irradiance_texture,
    refine_penumbrae,
)
from .light.raytrace import RayScene, offset_ray_origin
from .light.reflection_law import ReflectionLaw, angular_correction
from .light.samples import interleave_period, light_direction, sobol_points
from .light.specular import torrance_sparrow
from .light.thin_parts import FarSide, ThinMedia, far_side
from .options import AOVS, DATA_AOVS, RenderOptions
from .scene import SceneData, SceneDelegate, SceneMesh, content_hash
from .shading import (
    albedo_image,
    albedo_texels,
    albedo_texture,
    bilinear,
    bilinear_of,
    exitant_radiance,
    mean_albedo,
    media_summary,
    mesh_hits,
    normal_map,
    ray_owners,
    skin_media,
    surface_flux,
    surface_radiance,
    times_albedo_weight,
)
from .surface.resample import (
    EXACT_POWERS,
)
from .surface.texture_maps import (
    TextureMaps,
    rasterize,
    texel_rows,
    texels_in_blocks,
    vertex_normals,
)
from .surface.unwrap import triangulate
from .surface.uvs import unwrap_and_write_back, usable_uvs, uv_triangles

EDGE_SAMPLES = ((0.125, -0.375), (0.375, 0.125), (-0.125, 0.375), (-0.375, -0.125))
"""Sub-pixel offsets (pixels) of a silhouette pixel's camera rays: the 4-rook rotated
grid, one sample in every row and column of a 4 x 4 subdivision."""


class Renderer:
    """Renders frames of a stage; texture-space work is cached across frames and edits."""

    def __init__(self, stage: Any, options: RenderOptions,
                 progress: Callable[[str], None] | None = None) -> None:
        self.stage = stage
        self.options = options
        self.delegate = SceneDelegate(stage, options.camera)
        self.progress = progress or (lambda _msg: None)
        # large buffers ask for huge pages only where their first touch is not dearer
        # (huge_pages); numpy's arrays too, unless the user set numpy's own switch
        self.huge_pages = huge_pages_choice()
        if not self.huge_pages.use and "NUMPY_MADVISE_HUGEPAGE" not in os.environ:
            apply_to_numpy(False)
        self._cache: dict[str, Any] = {}
        self._cache_lock = threading.Lock()  # the diffusion layout's task runs on a thread
        self.textures: list[SkinTextures] = []
        self._prewarmed = False
        self.last_frame = False
        """Whether no frame follows this one (:func:`render_files`' last): its texture
        maps' position and normal, and its seam layout's surface, go as soon as its
        irradiance and layout are made, rather than stay for a next frame."""

    def close(self) -> None:
        self.delegate.close()

    def clear_cache(self) -> None:
        """Drop every cached task result (texture-space maps, irradiance, diffusion, and
        the diffusion layout's device buffers): the next frame recomputes them."""
        self._cache.clear()

    def _cached(self, log: TaskLog, task: str, key: str, compute: Callable[[], Any],
                report: bool = True) -> Any:
        """``compute()``'s value, kept under ``task`` and ``key`` for later frames (one
        generation per task); ``report``: name the task to the progress callback."""
        full = f"{task}:{key}"
        with self._cache_lock:
            if full in self._cache:
                log.cached.append(task)
                return self._cache[full]
        if report:
            self.progress(task)
        start = time.perf_counter()
        value = compute()
        log.seconds[task] = log.seconds.get(task, 0.0) + time.perf_counter() - start
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith(f"{task}:")]:
                del self._cache[k]  # one generation per task: memory stays bounded
            self._cache[full] = value
        return value

    # ---- texture-space tasks
    def _uvs(self, log: TaskLog, mesh: SceneMesh) -> tuple[NDArray[Any], NDArray[np.int32]]:
        why = usable_uvs(mesh)
        if why is None:
            return mesh.uv, uv_triangles(mesh)  # type: ignore[return-value]

        def compute() -> tuple[NDArray[Any], NDArray[np.int32]]:
            uv, uv_tris, measures = unwrap_and_write_back(
                self.stage, mesh, why, self.options.write_uvs, self.progress)
            log.measures["unwrap"] = measures
            return uv, uv_tris

        return self._cached(log, "unwrap", mesh.geometry_key(), compute)

    @property
    def device(self) -> Device:
        """The OpenCL device the options ask for (probed at the first request in this
        process), which every texture-space step is handed."""
        return open_device(self.options.device)

    def _kernel_plan(self, scene: SceneData) -> list[Callable[[], Any]]:
        """The device kernels this render will need (:func:`~.kernel_plan.kernel_plan`)."""
        # each skin mesh's interleaving period where its UVs are known before the render
        # (an unwrap's are not: theirs, if not 2, are built at their first launch)
        periods = {self._interleaving(scene, m, m.uv, uv_triangles(m), triangulate(m.mesh))[0]
                   if usable_uvs(m) is None else 2 for m in scene.skin}
        regions = {0 if m.region_weights is None else m.region_weights.shape[1]
                   for m in scene.skin}
        return kernel_plan(self.device, self.options, scene.lights, periods, regions)

    def skin_textures(self, log: TaskLog, scene: SceneData, mesh: SceneMesh) -> SkinTextures:
        """A skin mesh's texture-space maps (the task texture_maps; its UVs made first where
        they are missing or unusable), with the keys the later tasks cache under: the
        first texture-space step, for a report or a benchmark that runs some of them."""
        opts = self.options
        uv, uv_tris = self._uvs(log, mesh)
        tris = triangulate(mesh.mesh)
        key = content_hash(mesh.mesh.points, tris, uv, uv_tris, mesh.region_weights
                           if mesh.region_weights is not None else 0, opts.texture_size,
                           scene.meters_per_unit)
        maps = self._cached(log, "texture_maps", key, lambda: rasterize(
            mesh.mesh.points, tris, uv, uv_tris, opts.texture_size, scene.meters_per_unit,
            mesh.region_weights, self.device))
        albedo_key = content_hash(key, mesh.albedo, scene.working_colorspace)
        period, per_pixel = self._interleaving(scene, mesh, uv, uv_tris, tris)
        irradiance_key = content_hash(
            mesh.geometry_key(), opts.texture_size, scene_geometry_key(scene),
            [lt.key() for lt in scene.lights], opts.light_samples, opts.ior, mesh.albedo,
            scene.working_colorspace, opts.seed, opts.shadow_sampling, opts.light_sequence,
            period if opts.shadow_sampling != "full" else 0,  # full sampling has none
            opts.transmission and mesh.fits_key())
        return SkinTextures(mesh, uv, uv_tris, tris, maps, period=period,
                            texels_per_pixel=per_pixel,
                            keys={"maps": key, "albedo": albedo_key,
                                  "irradiance": irradiance_key})

    def _interleaving(self, scene: SceneData, mesh: SceneMesh, uv: NDArray[Any],
                      uv_tris: NDArray[Any], tris: NDArray[Any]) -> tuple[int, float]:
        """The interleaving period of a skin mesh's shadow rays
        (:func:`~.lighting.interleave_period` of its texels per pixel, or up to the
        option's period) and its texels per pixel (0 without a camera)."""
        opts = self.options
        per_pixel = 0.0 if scene.camera is None else texels_per_pixel(
            mesh.mesh.points, tris, uv, uv_tris, opts.texture_size, scene.camera,
            opts.resolution[0])
        points = sobol_points(opts.light_samples) if opts.light_sequence == "sobol" \
            else opts.light_samples
        return interleave_period(per_pixel, points, opts.interleave_period), per_pixel

    def albedo(self, log: TaskLog, scene: SceneData, tex: SkinTextures) -> None:
        """``tex``'s albedo image and, where the split's weights need it, its map (a
        split of 0.5, the default, does not): after the irradiance, which does not read
        them (a painted albedo's map held 201 MB beside the irradiance's peak at texture
        4096; making it took 0.4 s)."""
        key = tex.keys["albedo"]
        image, source = self._cached(log, "albedo", key, lambda: albedo_image(
            tex.mesh, scene.working_colorspace))
        log.measures["albedo_source"] = source
        tex.albedo_image = image
        a = self.options.albedo_split
        if a not in EXACT_POWERS or 1.0 - a not in EXACT_POWERS:
            tex.albedo = self._cached(log, "albedo_map", key, lambda: albedo_texture(
                image, self.options.texture_size))

    def irradiance(self, log: TaskLog, scene: SceneData, tex: SkinTextures,
                   rays: RayScene, dome_textures: dict[str, NDArray[np.float32]],
                   release: _BothArrived | None = None,
                   after_rays: Callable[[], None] | None = None) -> None:
        """``tex``'s irradiance and visibility maps. In a last frame (``release``) the
        position and normal maps go once the rows are taken and the seam layout needs
        them no more (0.4 GB at texture 4096); the filter makes a normal map again from
        the rows. ``after_rays``: called once the shadow rays are cast."""
        opts = self.options
        maps = tex.maps
        covered = maps.triangle >= 0
        key = tex.keys["irradiance"]
        period = tex.period

        def compute() -> Any:
            nonlocal maps
            # covered texels by flat index and np.take / np.put: a boolean mask over
            # (H, W, 3) maps gathers and scatters rows several times slower. In blocks,
            # so that their rays go to Embree in a coherent order as they are
            texel = texels_in_blocks(covered)
            interleave = np.take(interleave_classes(covered.shape, period), texel) \
                if opts.shadow_sampling != "full" else None
            positions, normals = (texel_rows(m, texel) for m in maps.surface)
            regions = texel_rows(maps.region_weights, texel) \
                if opts.transmission and maps.region_weights is not None else None
            if release is not None:
                maps = maps.without_surface(*self._keeps())
                release.arrive("irradiance")
            boundary = self._skin_boundary(log, scene, tex)
            res = irradiance_texture(positions, normals, scene.lights, rays,
                                     opts.light_samples, boundary,
                                     opts.seed, dome_textures, interleave, opts.light_sequence,
                                     coherent=True, period=period, device=self.device)
            through, first = self._through_volume(
                log, scene, tex, rays, positions, normals, texel, regions) \
                if opts.transmission else (None, None)
            del regions
            penumbra: dict[str, int] = {}  # texels refined per light (adaptive)
            if opts.shadow_sampling == "adaptive" and res.interleaved:
                res, refined = refine_penumbrae(
                    res, covered, positions, normals, interleave, scene.lights, rays,
                    opts.light_samples, boundary, opts.seed, dome_textures,
                    opts.light_sequence, texel, coherent=True, period=period,
                    device=self.device)
                penumbra = {path: int(where.size) for path, where in refined.items()}
            if after_rays is not None:
                after_rays()
            visibility = res.visibility
            filtered = bool(interleave is not None and res.interleaved and visibility)
            normal = None if not filtered or maps.normal is not None else \
                normal_map(normals, texel, covered.shape)
            # the rays are cast: the points go before the filter's planes (0.18 GB at
            # texture 4096)
            del positions, normals
            # the gutter's sources on a thread beside the filter and the planes, whose
            # numpy steps leave a core idle (0.2-0.3 s at texture 4096 on the main one)
            coverage = maps.coverage  # made here, not there
            gutter = beside(lambda: prepare_dilation(coverage), "skinpipe-gutter")
            if filtered:  # the sums of the visibility as traced are not made at all
                visibility = interleaved_visibility(res, maps, texel, period, normal,
                                                    self.device)
                entering = res.entering_with(visibility)
            else:
                entering = res.entering
            entering = through_volume(entering, first, through, scene.lights, res,
                                      visibility if filtered else res.visibility, log.measures)
            del normal, through, first
            notes = (res.skipped, res.rays, res.seconds, penumbra)
            # the per-light sums go before the planes and their push-pull (0.3 GB at
            # texture 4096)
            del interleave, res
            filled, vis = _filled_planes(self.device, scene, maps, covered, texel, entering,
                                         visibility, gutter)
            # the cache keeps what later tasks read, not the per-light arrays (~100 MB);
            # the irradiance itself is the filled one on the charts (SkinTextures)
            return filled[..., :3], vis, notes

        filled, vis, notes = self._cached(log, "irradiance", key, compute)
        tex.irradiance_filled, tex.visibility = filled, vis
        _note_irradiance(log, opts, tex, int(covered.sum()), notes)

    @staticmethod
    def _hit_uvs(scene: SceneData, tex: SkinTextures, cam: CameraHits,
                 owners: dict[str, NDArray[Any]]) -> dict[str, NDArray[np.float64]]:
        """The texture coordinates of the camera's hits on ``tex``'s mesh, by part
        ('center', 'edge'); ``owners``: each part's :func:`ray_owners`."""
        mesh = scene.meshes.index(tex.mesh)
        return {part: hit_uvs(tex, *mesh_hits(owners[part], hits, mesh)[1:])
                for part, hits in (("center", cam.hits), ("edge", cam.edge_hits))}

    def _look_up_at_hits(self, tex: SkinTextures, uvs: dict[str, NDArray[np.float64]]
                         ) -> None:
        """``tex.at_hits``: what the shading reads of the irradiance and the lights'
        visibility maps (their push-pulled planes: 268 MB at texture 4096 with one
        shadowed light) at the camera's hits on ``tex``'s mesh (:meth:`_hit_uvs`, kept in
        ``tex.hit_uv`` for the shading), the same bilinear lookups, so that the diffusion
        lets the maps go once it has read the irradiance (:meth:`_release_irradiance`)
        rather than hold them through its peak."""
        tex.hit_uv.update(uvs)
        tex.at_hits = {part: self._irradiance_lookups(tex, uv) for part, uv in uvs.items()}

    def _irradiance_lookups(self, tex: SkinTextures, uv: NDArray[Any]
                            ) -> dict[str, NDArray[np.float32]]:
        """What the shading reads of ``tex``'s irradiance ('irradiance', (N, 3), for its
        AOV), albedo ('albedo', (N, 3), likewise) and each light's visibility (by light
        path, (N,), for the specular lobe) at texture coordinates ``uv`` (N, 2): the AOVs
        asked for need, bilinear lookups in the push-pulled maps and the albedo's (made
        from its image where the map was not made)."""
        wanted = set(self.options.aovs)
        got: dict[str, NDArray[np.float32]] = {}
        law = self._angular_law and bool(wanted & {"beauty", "diffuse"})
        # the angular law and the light summed on the surface scale by the albedo
        if "albedo" in wanted or law or (wanted & {"beauty", "diffuse"} and
                                         self.options.scattering):
            assert tex.albedo_image is not None
            size = self.options.texture_size
            got["albedo"] = bilinear_of(albedo_texels(tex.albedo_image, size), (size, size),
                                        uv)
        if "irradiance" in wanted:
            assert tex.irradiance_filled is not None
            got["irradiance"] = bilinear(tex.irradiance_filled, uv)
        if wanted & {"beauty", "specular"} or law:
            for path, plane in tex.visibility.items():
                got[path] = bilinear(plane, uv)[:, 0]
        return got

    def _release_albedo(self, tex: SkinTextures) -> None:
        """Let ``tex``'s albedo map go (out of the cache too: a later render makes it
        again) once its weight before the blur is taken and the shading's lookups of it
        (:meth:`_look_up_at_hits`); its image stays for the weight after the blur
        (:func:`~.resample.times_resampled_power`)."""
        with self._cache_lock:
            self._cache.pop(f"albedo_map:{tex.keys['albedo']}", None)
        tex.albedo = None

    def _release_irradiance(self, tex: SkinTextures) -> None:
        """Let ``tex``'s filled irradiance and visibility maps go (out of the cache too:
        a later render makes them again) once the shading's lookups of them are taken
        (:meth:`_look_up_at_hits`) and the diffusion has read the irradiance."""
        with self._cache_lock:
            self._cache.pop(f"irradiance:{tex.keys['irradiance']}", None)
        tex.irradiance_filled, tex.visibility = None, {}

    def _release_maps(self, tex: SkinTextures) -> None:
        """Let ``tex``'s position and normal maps go (and the stretch and region maps,
        :meth:`_keeps`) in a render's last frame, once the irradiance has taken its
        texels' rows and the seam layout beside needs them no more (0.4-0.7 GB at
        texture 4096): out of the cache too, so that a later render makes them again.
        Safe from the layout's thread (:class:`_BothArrived`)."""
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith("texture_maps:")]:
                del self._cache[k]
            tex.maps = tex.maps.without_surface(*self._keeps())

    def _release_layout(self, layout: DiffusionLayout) -> None:
        """Let a last frame's seam layout's surface go once its tiles are made
        (:meth:`~.diffusion.DiffusionLayout.release_surface`; out of the cache: it makes
        no tiles any more)."""
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith("diffusion_layout:")]:
                del self._cache[k]
            layout.release_surface()

    def _release_surface(self, tex: SkinTextures, layout: DiffusionLayout | None) -> None:
        """:meth:`_release_maps` and :meth:`_release_layout` (each again a no-op)."""
        self._release_maps(tex)
        if layout is not None:
            self._release_layout(layout)

    def _keeps(self) -> tuple[bool, bool]:
        """Whether a last frame's maps keep their stretch maps and their region weights
        past the irradiance: both for the gather blur, which reads them, and each for
        its texture output (the recursive blur's layout makes the region weights again
        per texel, :class:`~.texture_maps.TexelRegions`)."""
        opts = self.options
        gather = opts.blur == "gather"
        return (gather or "stretch" in opts.texture_outputs,
                gather or "region" in opts.texture_outputs)

    def _terms(self, tex: SkinTextures) -> tuple[DiffusionTerms, float]:
        """The blur schedule of a skin mesh's fits at its texture's median texel size
        (mm), which it returns too."""
        maps, opts = tex.maps, self.options
        texel_mm = float(np.median(np.sqrt(maps.mm_per_texel_u * maps.mm_per_texel_v)[
            maps.triangle >= 0]))
        # blurs narrower than half a texel change nothing a texture can hold
        return kept_diffusion_terms(tex.mesh.fits, opts.variance_grid, opts.single_profile,
                                    floor_mm2=(0.5 * texel_mm) ** 2), texel_mm

    def _diffusion_key(self, tex: SkinTextures, terms: DiffusionTerms) -> str:
        opts = self.options
        return content_hash(tex.keys["irradiance"], tex.keys["albedo"], terms.variances_mm2,
                            terms.weights, opts.albedo_split, opts.scattering, opts.blur)

    def _layout_beside(self, log: TaskLog, tex: SkinTextures, terms: DiffusionTerms,
                       rays: RayScene, mesh_index: int, geometry_key: str,
                       release: _BothArrived | None = None
                       ) -> Future[DiffusionLayout] | None:
        """The diffusion layout's task for a recursive blur, started on a thread to run
        beside the irradiance (None for other blurs): it reads only the texture maps and
        the ray scene, and each leaves the cores idle part of the time (single-threaded
        numpy steps, waits for the device) that the other fills: 5-14% of the demo
        scene's render at texture 2048 and 4096.

        The layout depends on the UV layout and the geometry only: it is made once for
        every frame, light and set of terms (a task of its own, cached); the charts'
        tiles cross the UV seams (chart_tiles), each set of terms adds the tiles and
        margins it reaches (prepare). A cached layout that holds the terms' tiles is
        back at once. With ``options.layout_cache`` the tiles come from disk where an
        earlier process made them (:mod:`.tile_store`), and go there where this one
        makes them; ``render.json``'s ``tile_store`` says which.

        The layout reads no position or normal map: where it makes tiles it makes the
        surface at its margins' start texels from the triangles
        (:class:`~.texture_maps.TexelSurface`). In a render's last frame (``release``) it
        says so once it holds the maps less their surface, so that they may go as soon
        as the irradiance has taken its texels' rows (:meth:`_release_maps`), and its own
        surface goes as it ends."""
        opts = self.options
        if not (opts.scattering and opts.blur == "recursive") or \
                f"diffusion:{self._diffusion_key(tex, terms)}" in self._cache:
            return None  # a gather blur needs none; a cached diffusion needs none now

        key = content_hash(tex.keys["maps"], geometry_key, mesh_index)

        def layout(maps: TextureMaps, store: TileStore | None) -> DiffusionLayout:
            return DiffusionLayout(self.device, maps.mm_per_texel_u, maps.mm_per_texel_v,
                                   maps.coverage, maps.region_weights,
                                   chart_layout(self.device, maps, tex.mesh.mesh.points,
                                                tex.tris, tex.uv, tex.uv_tris, rays,
                                                mesh_index,
                                                tex.mesh.mesh.meters_per_unit * 1000.0),
                                   store, maps.texel_regions,
                                   maps.triangle_stretch() if maps.tri_mm is not None
                                   else None)

        def make() -> DiffusionLayout:
            try:
                # the maps less their surface, taken before it says it needs no more of
                # them: once made, the layout reads no map but the triangle map (its
                # surface and texel sizes come from the triangles)
                maps = tex.maps.without_surface()
                if release is not None:
                    release.arrive("layout")
                store = None if opts.layout_cache is None else \
                    TileStore(Path(opts.layout_cache), key, self.device)
                prepared = self._cached(log, "diffusion_layout", key,
                                        partial(layout, maps, store), report=False)
                del maps
                # other terms (one profile for every region) add the tiles they lack
                start = time.perf_counter()
                prepared.prepare(terms.variances_mm2,
                                 texels_on_surface="radiosity" in opts.texture_outputs)
                log.seconds["diffusion_layout"] = (log.seconds.get("diffusion_layout", 0.0)
                                                   + time.perf_counter() - start)
                if release is not None:
                    self._release_layout(prepared)
                return prepared
            finally:
                if release is not None:
                    release.arrive("layout")

        return beside(make, "skinpipe-layout")

    def _diffusion(self, log: TaskLog, tex: SkinTextures, terms: DiffusionTerms,
                   texel_mm: float, layout: Future[DiffusionLayout] | None) -> None:
        opts = self.options
        assert tex.irradiance_filled is not None
        key = self._diffusion_key(tex, terms)
        prepared: DiffusionLayout | None = None
        if layout is not None:
            if not layout.done():
                self.progress("diffusion_layout")
            start = time.perf_counter()
            prepared = layout.result()
            log.measures["diffusion_layout"] = {
                "beside": "irradiance", "waited_s": time.perf_counter() - start}
        if self.last_frame:
            self._release_surface(tex, prepared)
        maps = tex.maps  # after the release: not the maps that still hold the surface

        albedo = tex.albedo  # None: the weights come from its image

        def compute() -> Any:
            nonlocal albedo
            a = opts.albedo_split
            pre = tex.irradiance  # a new array: weighted in place
            assert pre is not None
            if tex.at_hits is not None:  # the shading's lookups are taken
                self._release_irradiance(tex)
            times_albedo_weight(pre, albedo, tex.albedo_image, a, self.device)
            if albedo is not None and tex.at_hits is not None and 1.0 - a in EXACT_POWERS:
                # the weight after the blur comes from the albedo's own image: the map
                # goes before the diffusion's peak (201 MB at texture 4096)
                albedo = None
                self._release_albedo(tex)
            # the heap the frame's earlier steps freed goes back to the system before
            # the diffusion's work buffers come (0.18 GB at texture 4096)
            release_freed_heap()
            cov = maps.coverage
            # the blur moves flux, it must not create or lose it (chart borders included);
            # points on the surface weigh texels by their true areas (sheared charts)
            on = None if prepared is None else prepared.surface
            flux = partial(surface_flux, maps=maps) if on is None else partial(texel_flux, on)
            flux_in = flux(pre)
            skipped: list[str] = []
            surface = full = None
            if opts.scattering:
                if prepared is not None:  # a radiosity output holds the surface's light too
                    out, surface, full, stats = diffuse_on_surface(
                        prepared, pre, terms.variances_mm2, terms.weights,
                        texels="radiosity" in opts.texture_outputs)
                    if self.last_frame:  # its buffers stayed beside the push-pull's
                        prepared.release_work()
                else:
                    out, stats = diffuse_gather(pre, maps.mm_per_texel_u, maps.mm_per_texel_v,
                                                cov, terms.variances_mm2, terms.weights,
                                                maps.region_weights, self.device)
                del pre  # texture-sized arrays go as soon as they are used (peak memory)
                skipped, passes = stats.skipped, stats.passes
                work = {"pyramid_levels": stats.levels, "full_resolution_blurs": stats.full_blurs,
                        "surface_terms": stats.surface_terms}
            else:
                out, passes, work = pre, 0, {}
                skipped = ["diffusion: scattering off (texture-mapped irradiance only)"]
            flux_out = flux(out) + (0.0 if surface is None else surface.flux)
            energy = flux_out / flux_in if flux_in > 0 else 1.0
            radiance, full = (None if rgb is None else exitant_radiance(
                rgb, albedo, tex.albedo_image, 1.0 - a, cov, self.device) for rgb in (out, full))
            return radiance, surface, full, skipped, passes, energy, work

        radiance, surface, full, skipped, passes, energy, work = self._cached(
            log, "diffusion", key, compute)
        tex.radiance, tex.surface_light = radiance, surface
        tex.radiosity = radiance if full is None else full
        log.skipped += [f"{tex.mesh.path}: {s}" for s in terms.notes + skipped]
        log.measures["diffusion"] = {
            "variances_mm2": terms.variances_mm2.tolist(), "blur": opts.blur,
            "blur_passes": passes, **work, "energy_ratio": energy,
            "grid_error_eq2c": terms.error, "grid_edge_error": terms.edge_error,
            "mm_per_texel_median": texel_mm}

    def texture_space(self, log: TaskLog, scene: SceneData, mesh: SceneMesh, rays: RayScene,
                      dome_textures: dict[str, NDArray[np.float32]] | None = None,
                      camera: Callable[[], tuple[CameraHits, dict[str, NDArray[Any]]]]
                      | None = None
                      ) -> SkinTextures:
        """A skin mesh's texture-space tasks for a frame of ``scene`` (the ray scene
        ``rays`` holds every mesh of it): texture maps, irradiance, albedo and the
        diffused radiance, the seam layout made beside the irradiance; each task's
        seconds, cached tasks and measures go to ``log``. With ``camera`` (which gives the
        camera's hits and, per part, their :func:`ray_owners`), a last frame that writes no
        irradiance texture looks the irradiance and visibility up at the hits before the
        diffusion and lets the maps go (:meth:`_look_up_at_hits`)."""
        tex = self.skin_textures(log, scene, mesh)
        terms, texel_mm = self._terms(tex)
        # a last frame lets the maps the irradiance and the layout read go once both are
        # done with them
        release = _BothArrived(lambda: self._release_maps(tex)) if self.last_frame else None
        layout = self._layout_beside(log, tex, terms, rays, scene.meshes.index(mesh),
                                     scene_geometry_key(scene), release)
        if layout is None and release is not None:
            release.arrive("layout")
        look_up = camera is not None and self.last_frame and \
            "irradiance" not in self.options.texture_outputs
        uvs: list[Future[dict[str, NDArray[np.float64]]]] = []

        def hit_uvs() -> dict[str, NDArray[np.float64]]:
            assert camera is not None
            return self._hit_uvs(scene, tex, *camera())

        try:
            # the camera's rays and the hits' uvs need no irradiance: on a thread once the
            # rays are cast, while the filter's numpy steps leave a core idle (0.2 s of the
            # main thread at texture 4096)
            self.irradiance(log, scene, tex, rays, dome_textures or {}, release,
                             (lambda: uvs.append(beside(hit_uvs, "skinpipe-camera")))
                             if look_up else None)
        except BaseException:
            # no thread outlives its frame, not even on errors
            wait([*uvs, *([] if layout is None else [layout])])
            raise
        self.albedo(log, scene, tex)
        if look_up:
            self._look_up_at_hits(tex, uvs[0].result() if uvs else hit_uvs())
        self._diffusion(log, tex, terms, texel_mm, layout)
        store = None if layout is None else layout.result().store
        if store is not None:  # its writes ran beside the diffusion
            store.flush()
            log.measures["tile_store"] = store.summary()
        return tex

    # ---- per frame
    def render(self, time_code: Any = None) -> tuple[dict[str, NDArray[np.float32]], TaskLog]:
        """One frame: AOV images (H, W, 4 for beauty with alpha; H, W, 3 otherwise)."""
        log = TaskLog()
        t0 = time.perf_counter()
        scene = self.delegate.sync(time_code)
        log.seconds["sync"] = time.perf_counter() - t0
        if not scene.meshes:
            raise InputError("the stage has no visible mesh to render")
        if not scene.skin:
            raise InputError("no mesh with skin profiles (SkinProfileRegionsAPI + skin:profiles)"
                             " on the stage")
        if not scene.lights:
            raise InputError("the stage has no UsdLux light (DistantLight, SphereLight, "
                             "RectLight or DomeLight): nothing would be lit")
        if scene.camera is None:
            raise InputError("the stage has no UsdGeomCamera (add one, or pass --camera)")
        if not self._prewarmed:  # later frames find every kernel built
            start_prewarm(self.device, self._kernel_plan(scene))
            self._prewarmed = True
        rays = self._cached(log, "bvh", scene_geometry_key(scene), lambda: RayScene(
            [(m.mesh.points, triangulate(m.mesh)) for m in scene.meshes]))
        domes = {}
        for light in scene.lights:
            if light.kind == "dome" and light.texture:
                domes[light.path] = self._cached(log, f"dome:{light.path}", str(light.texture),
                                                 lambda lt=light: read_image(lt.texture).pixels)
        seen = [i for i, m in enumerate(scene.meshes) if m.camera_visible]
        if not seen:
            raise InputError("every mesh on the stage is hidden from the camera")
        camera_rays = rays
        if len(seen) < len(scene.meshes):  # occluders that only cast shadows
            def build() -> RayScene:
                view = RayScene([(scene.meshes[i].mesh.points,
                                  triangulate(scene.meshes[i].mesh)) for i in seen])
                view.owner[:, 0] = np.asarray(seen)[view.owner[:, 0]]  # scene's mesh index
                return view
            camera_rays = self._cached(log, "bvh_camera", content_hash(
                scene_geometry_key(scene), seen), build)
            log.skipped.append("camera rays: " + ", ".join(
                m.path for m in scene.meshes if not m.camera_visible) + " cast shadows only")
        # the last frame's texture-space results, for outputs; the camera's hits are
        # made where a last frame looks up what it needs of the irradiance there, before
        # the diffusion (Renderer._look_up_at_hits): made first, they waited for the
        # kernels' prewarm (0.5-0.8 s against 0.16 at texture 4096)
        made: list[tuple[CameraHits, dict[str, NDArray[Any]]]] = []
        making = threading.Lock()

        def camera() -> tuple[CameraHits, dict[str, NDArray[Any]]]:
            """The camera's hits and each part's (mesh, triangle) of them: once a frame
            (the log counts the task once), for the lookups and the shading; from any
            thread (a caller waits for one that is making them)."""
            with making:
                if not made:
                    cam = self._camera_hits(scene, log, camera_rays)
                    made.append((cam, {part: ray_owners(camera_rays, hits[0]) for part, hits
                                       in (("center", cam.hits), ("edge", cam.edge_hits))}))
            return made[0]

        skins = self.textures = [self.texture_space(log, scene, mesh, rays, domes, camera)
                                 for mesh in scene.skin]
        self.progress("shade")
        t0 = time.perf_counter()
        images = self._shade(scene, skins, rays, log, *camera())
        log.seconds["shade"] = time.perf_counter() - t0
        log.measures["huge_pages"] = asdict(self.huge_pages)
        log.measures["rays"] = {"counts": rays.stats.rays,
                                "mrays_per_s": rays.stats.mrays_per_s()}
        return images, log

    def _camera_hits(self, scene: SceneData, log: TaskLog, camera_rays: RayScene
                     ) -> CameraHits:
        """The camera's rays through the pixel centres and their first hits, the
        silhouette pixels (a 3 x 3 neighbourhood with both geometry and background) and
        their :data:`EDGE_SAMPLES` rays and hits: the same for every render of one camera,
        image size and geometry (the demo's three renders, a relit shot), so cached."""
        width, height = self.options.resolution
        cam = scene.camera
        assert cam is not None

        def compute() -> CameraHits:
            origins, dirs = cam.rays(width, height)
            hits = camera_rays.intersect(origins, dirs)
            mask = (hits[0] >= 0).reshape(height, width)
            padded = np.pad(mask, 1, mode="edge")
            windows = [padded[dy:dy + height, dx:dx + width]
                       for dy in range(3) for dx in range(3)]
            edge = np.flatnonzero((np.any(windows, axis=0) & ~np.all(windows, axis=0)).ravel())
            py, px = np.divmod(edge, width)
            offs = np.asarray(EDGE_SAMPLES)
            sx = (px[:, None] + 0.5 + offs[None, :, 0]).ravel()
            sy = (py[:, None] + 0.5 + offs[None, :, 1]).ravel()
            sub_origins, sub_dirs = cam.rays_at(sx, sy, width, height)
            return CameraHits(origins, dirs, hits, edge, sub_origins, sub_dirs,
                              camera_rays.intersect(sub_origins, sub_dirs))

        seen = [m.camera_visible for m in scene.meshes]
        return self._cached(log, "camera_hits", content_hash(
            cam.key(), width, height, scene_geometry_key(scene), seen), compute)

    def _shade(self, scene: SceneData, skins: list[SkinTextures], rays: RayScene,
               log: TaskLog, cam: CameraHits, owners: dict[str, NDArray[Any]]
               ) -> dict[str, NDArray[np.float32]]:
        """The AOV images: one camera ray through each pixel centre, and where a pixel's
        3 x 3 neighbourhood holds both geometry and background (a silhouette), the
        pixel is shaded again at :data:`EDGE_SAMPLES` (a rotated grid) and its alpha is
        their coverage, its colours their mean (premultiplied). ``owners``: each part's
        :func:`ray_owners` of the hits."""
        opts = self.options
        width, height = opts.resolution
        out, hit = self._shade_rays(scene, skins, rays, owners["center"], cam.origins,
                                    cam.dirs, cam.hits, log, "center")
        alpha = hit.astype(np.float32)
        edge = cam.edge
        if edge.size:
            sub, sub_hit = self._shade_rays(scene, skins, rays, owners["edge"],
                                            cam.edge_origins, cam.edge_dirs, cam.edge_hits,
                                            log, "edge")
            k = len(EDGE_SAMPLES)
            for a in AOVS:  # colours: the samples' mean; a region index stays the centre's
                out[a][edge] = sub[a].reshape(edge.size, k, 3).mean(axis=1)
            alpha[edge] = sub_hit.reshape(edge.size, k).mean(axis=1)
            log.measures["edge_pixels"] = {"pixels": int(edge.size), "samples": k}
        images = {}
        for a in opts.aovs:
            img = out[a].reshape(height, width, -1)
            if a == "beauty":
                img = np.concatenate([img, alpha.reshape(height, width, 1)], axis=2)
            images[a] = img
        skipped_aovs = [a for a in AOVS + DATA_AOVS if a not in opts.aovs]
        if skipped_aovs:
            log.skipped.append(f"AOVs not asked for: {', '.join(skipped_aovs)}")
        return images

    def _shade_rays(self, scene: SceneData, skins: list[SkinTextures], rays: RayScene,
                    owner: NDArray[Any], origins: NDArray[Any], dirs: NDArray[Any],
                    hits: tuple[NDArray[Any], ...], log: TaskLog, part: str
                    ) -> tuple[dict[str, NDArray[np.float32]], NDArray[np.bool_]]:
        """The AOVs asked for (the others stay zero) for camera rays (origins, dirs) and
        their ``hits`` among the meshes the camera sees (``owner``: each hit's mesh and
        triangle, :func:`ray_owners`; shadow rays against ``rays``, every mesh), and which
        rays hit. ``part``: which of the camera's rays they are ('center' or 'edge'), for
        what was taken of them before (``at_hits``, ``hit_uv``)."""
        opts = self.options
        wanted = set(opts.aovs)
        prim, _, _, dist = hits
        n_pix = origins.shape[0]
        out = {a: np.zeros((n_pix, 3), np.float32) for a in AOVS}
        out["region"] = np.full((n_pix, 1), -1.0, np.float32)
        mesh_index = {m.path: i for i, m in enumerate(scene.meshes)}
        for m_i, mesh in enumerate(scene.meshes):
            sel, tri_idx, b = mesh_hits(owner, hits, m_i)
            if sel.size == 0:
                continue
            tris = triangulate(mesh.mesh)
            pos = origins[sel] + dirs[sel] * dist[sel, None]
            normals = self._cached(log, f"normals:{mesh.path}", mesh.geometry_key(),
                                   lambda m=mesh, t=tris: vertex_normals(m.mesh.points, t))
            n = (normals[tris[tri_idx]] * b).sum(axis=1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            view = -dirs[sel]
            # two-sided: a normal facing away from the camera is flipped
            flip = np.einsum("ij,ij->i", n, view) < 0
            n[flip] *= -1
            tex = next((s for s in skins if mesh_index[s.mesh.path] == m_i), None)
            if tex is None:
                self._shade_plain(scene, mesh, pos, n, sel, rays, out)
                continue
            uv = tex.hit_uv[part] if part in tex.hit_uv else hit_uvs(tex, tri_idx, b)
            at = self._irradiance_lookups(tex, uv) if tex.at_hits is None else \
                tex.at_hits[part]
            weights = None if mesh.region_weights is None else \
                (mesh.region_weights[tris[tri_idx]] * b).sum(axis=1)
            # only the AOVs asked for (the demo's comparison renders ask for beauty alone:
            # the albedo, irradiance and region lookups were 0.35 s of a 1.1 s shade)
            if wanted & {"beauty", "diffuse"}:
                n_dot_v = np.clip(np.einsum("ij,ij->i", n, view), 0, 1)
                leave = transmission(n_dot_v, opts.ior)[:, None]
                assert tex.radiance is not None
                radiance = bilinear(tex.radiance, uv)
                if tex.surface_light is not None:  # the wide terms, summed on the surface
                    radiance += surface_radiance(tex.surface_light, self.device,
                                                 pos * np.float32(scene.meters_per_unit * 1e3),
                                                 n, at["albedo"], 1.0 - opts.albedo_split)
                law = self._reflection_law(log, scene, tex) if self._angular_law else None
                if law is not None:
                    radiance += angular_correction(*law, scene.lights, pos, n, view, at,
                                                   at["albedo"], weights)
                out["diffuse"][sel] = radiance * leave
            if "albedo" in wanted:
                out["albedo"][sel] = at["albedo"]
            if "irradiance" in wanted:
                out["irradiance"][sel] = at["irradiance"]
            if "region" in wanted and weights is not None:
                out["region"][sel, 0] = np.argmax(weights, axis=1)
            if wanted & {"beauty", "specular"}:
                out["specular"][sel] = self._specular(scene, pos, n, view, at)
        out["beauty"] = out["diffuse"] + out["specular"]
        return out, prim >= 0

    @property
    def _angular_law(self) -> bool:
        """Whether the diffuse light follows :mod:`.light.reflection_law`: index-matched
        skin only (``--ior 1``; behind a boundary D holds closer: docs/render.md)."""
        return self.options.ior == 1.0

    def _mean_albedo(self, log: TaskLog, scene: SceneData, tex: SkinTextures
                     ) -> NDArray[np.float64]:
        """:func:`~.shading.mean_albedo` of ``tex``'s mesh (one read of its texture), kept."""
        return self._cached(log, f"mean albedo:{tex.mesh.path}", tex.keys["albedo"],
                            lambda: mean_albedo(tex.mesh, scene.working_colorspace),
                            report=False)

    def _skin_boundary(self, log: TaskLog, scene: SceneData, tex: SkinTextures
                       ) -> SkinBoundary:
        """The skin's dielectric boundary for its mean albedo, recorded in the log."""
        boundary = SkinBoundary.from_albedo(self._mean_albedo(log, scene, tex),
                                            self.options.ior)
        log.measures["boundary"] = {"ior": boundary.eta,
                                    "reduced_albedo": list(boundary.reduced_albedo)}
        return boundary

    def _media(self, log: TaskLog, scene: SceneData, tex: SkinTextures
               ) -> tuple[NDArray[np.float64], list[MediumEstimate] | None]:
        """:func:`~.shading.skin_media` of ``tex``'s mesh, kept across frames."""
        mesh = tex.mesh

        def compute() -> tuple[NDArray[np.float64], list[MediumEstimate] | None]:
            albedo, media, note = skin_media(mesh, self._mean_albedo(log, scene, tex))
            log.skipped += [note] if note else []
            log.measures["media"] = media_summary(media) if media is not None else None
            return albedo, media

        return self._cached(log, f"media:{mesh.path}",
                            content_hash(tex.keys["albedo"], mesh.fits_key()), compute,
                            report=False)

    def _reflection_law(self, log: TaskLog, scene: SceneData, tex: SkinTextures
                        ) -> tuple[ReflectionLaw, SkinBoundary] | None:
        """The angular law of ``tex``'s skin (:mod:`.light.reflection_law`) from its
        regions' media (:meth:`_media`), and the boundary the irradiance used; kept."""
        def compute() -> tuple[ReflectionLaw, SkinBoundary] | None:
            _, media = self._media(log, scene, tex)
            if media is None:
                return None
            return (ReflectionLaw(np.array([m.single_scattering_albedo for m in media]),
                                  np.array([m.anisotropy for m in media]), self.options.ior),
                    self._skin_boundary(log, scene, tex))

        key = content_hash(tex.keys["albedo"], self.options.ior, tex.mesh.fits_key())
        return self._cached(log, f"reflection law:{tex.mesh.path}", key, compute,
                            report=False)

    def _through_volume(self, log: TaskLog, scene: SceneData, tex: SkinTextures,
                        rays: RayScene, positions: NDArray[Any], normals: NDArray[Any],
                        texel: NDArray[Any], regions: NDArray[Any] | None
                        ) -> tuple[FarSide | None, FirstScatter | None]:
        """For the covered texels (rows of ``texel``) the thin parts' far sides
        (:func:`~.light.thin_parts.far_side`; None when none is within reach) and where
        their light first scatters (:class:`~.light.first_scatter.FirstScatter`), each
        texel's medium its regions' blend; (None, None) without the regions' media."""
        albedo, media = self._media(log, scene, tex)
        if media is None:
            return None, None
        thin = ThinMedia.of(media, albedo, scene.meters_per_unit)
        mesh, at, size = tex.mesh, scene.meshes.index(tex.mesh), self.options.texture_size
        start = time.perf_counter()
        far = far_side(rays, at, mesh.mesh.points, tex.tris, tex.uv, tex.uv_tris, size,
                       positions, normals, texel, thin, regions)
        log.measures["thin_parts"] = {"texels": int(far.rows.size), "reach": thin.reach,
                                      "seconds": time.perf_counter() - start}
        first = FirstScatter(rays, at, mesh.mesh.points, tex.tris, tex.uv, tex.uv_tris, size,
                             texel, np.take(tex.maps.triangle, texel), positions, normals,
                             thin.extinction_at(regions, texel.size), self.options.ior,
                             self.device)
        return (far if far.rows.size else None), first

    def _specular(self, scene: SceneData, pos: NDArray[Any], n: NDArray[Any],
                  view: NDArray[Any], at: dict[str, NDArray[np.float32]]
                  ) -> NDArray[np.float32]:
        """The specular lobe of each light but domes at the hits ``pos`` (normals ``n``,
        towards the camera ``view``), shadowed by its visibility there (``at``: by light
        path, :meth:`_irradiance_lookups` of these hits)."""
        opts = self.options
        spec = np.zeros((pos.shape[0], 3))
        for light in scene.lights:
            if light.path not in at or light.kind == "dome":
                continue
            l_dir, e_perp = light_direction(light, pos)
            h = l_dir + view
            h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
            nl = np.einsum("ij,ij->i", n, l_dir)
            f = torrance_sparrow(nl, np.einsum("ij,ij->i", n, view), np.einsum("ij,ij->i", n, h),
                                 np.einsum("ij,ij->i", view, h), opts.roughness, opts.rho_s)
            vis = at[light.path]
            spec += (f * np.maximum(nl, 0) * vis)[:, None] * e_perp
        return spec.astype(np.float32)

    def _shade_plain(self, scene: SceneData, mesh: SceneMesh, pos: NDArray[Any],
                     n: NDArray[Any], sel: NDArray[Any], rays: RayScene,
                     out: dict[str, NDArray[np.float32]]) -> None:
        """Meshes without skin profiles: Lambertian in their constant colour, direct light
        from each light's centre with one shadow ray (dome lights: unshadowed ambient)."""
        albedo = np.asarray(mesh.albedo.constant, np.float32)
        e = np.zeros((pos.shape[0], 3))
        origins = offset_ray_origin(pos, n)
        for light in scene.lights:
            if light.kind == "dome":
                e += light.radiance * math.pi * 0.5
                continue
            l_dir, e_perp = light_direction(light, pos)
            nl = np.maximum(np.einsum("ij,ij->i", n, l_dir), 0)
            far = np.full(pos.shape[0], np.inf) if light.kind == "distant" else \
                np.linalg.norm(light.position - pos, axis=1) * (1 - 1e-4)
            lit = nl > 0
            blocked = np.zeros(pos.shape[0], bool)
            blocked[lit] = rays.occluded(origins[lit], l_dir[lit], np.minimum(far[lit], 1e30))
            e += (nl * ~blocked)[:, None] * e_perp
        out["diffuse"][sel] = albedo * e / math.pi
        out["albedo"][sel] = albedo
        out["irradiance"][sel] = e


def _note_irradiance(log: TaskLog, opts: RenderOptions, tex: SkinTextures, covered: int,
                     notes: tuple[list[str], int, float, dict[str, int]]) -> None:
    """The irradiance task's notes (``notes``: what it skipped, rays cast, seconds, the
    texels refined per light) and measures in ``log``, over ``covered`` texels."""
    skipped, rays_cast, seconds, penumbra = notes
    skipped = [*skipped, *_period_notes(opts, tex.period)]
    log.skipped += [s for s in skipped if s not in log.skipped]
    log.measures["irradiance"] = {
        "rays": rays_cast, "seconds": seconds,
        "mrays_per_s": rays_cast / max(seconds, 1e-9) / 1e6,
        "rays_per_texel": rays_cast / max(covered, 1),
        "penumbra_texels": penumbra,
        "interleave_period": tex.period if opts.shadow_sampling != "full" else None,
        "texels_per_pixel": round(tex.texels_per_pixel, 3)}


def _period_notes(opts: RenderOptions, period: int) -> list[str]:
    """Why the interleaving period asked for was not used, if it was not."""
    if opts.interleave_period and period != opts.interleave_period and \
            opts.shadow_sampling != "full":
        return [f"interleave period {opts.interleave_period}: {opts.light_samples} light "
                f"samples cannot give each of its {opts.interleave_period ** 2} classes "
                f"one; period {period}"]
    return []


def _filled_planes(device: Device, scene: SceneData, maps: Any, covered: NDArray[Any],
                   texel: NDArray[Any],
                   entering: NDArray[Any], visibility: dict[str, NDArray[Any]],
                   gutter: Any) -> tuple[NDArray[np.float32], dict[str, NDArray[Any]]]:
    """The irradiance and the visibility the specular lobe looks up, from the covered
    texels' rows to full maps by one push-pull and the charts' dilation (dome lights
    light the lobe unshadowed: theirs is not needed)."""
    kinds = {lt.path: lt.kind for lt in scene.lights}
    spec = [p for p in visibility if kinds.get(p) != "dome"]
    planes = np.zeros((*covered.shape, 3 + len(spec)), np.float32)
    flat = planes.reshape(-1, planes.shape[-1])
    columns = [visibility[path] for path in spec]

    def scatter(rows: slice) -> None:  # in bands on the cores: a third of the time
        at = texel[rows]
        flat[at, :3] = entering[rows]  # by flat index: a strided mask's took 5x
        for i, column in enumerate(columns):
            flat[at, 3 + i] = column[rows]

    in_bands(scatter, texel.size)
    pulled = push_pull(planes, maps.coverage, in_place=True, device=device)
    gutter.result()
    filled = dilate_charts(pulled, maps.coverage)
    return filled, {path: filled[..., 3 + i] for i, path in enumerate(spec)}


def scene_geometry_key(scene: SceneData) -> str:
    return content_hash(*[m.geometry_key() for m in scene.meshes])
